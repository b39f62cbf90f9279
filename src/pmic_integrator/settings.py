"""User parameters of the ``pmic`` integrator: parsed, type-checked and range-checked once.

:class:`Settings` is frozen: every stage reads the same values for the integrator's
whole life. Types are checked as strictly as Mitsuba's own plugins check theirs (an
``integer`` parameter refuses a float such as 2.9 instead of truncating it, a string
refuses a number), and every error names the parameter, what it accepts and what it got.

Limits that depend on the scene (a ``lookup_radius`` too large or too small for it) are
checked by :func:`check_against_scene` before any photon is traced.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

METHODS = ("pmic", "photon_map", "irradiance_cache")
#: How ``pmic`` uses its cache at a camera path's diffuse vertices.
ESTIMATORS = ("final_gather", "first_hit", "adaptive")
#: Extra images (AOVs) ``pmic`` can output, in this channel order.
AOVS = {
    "albedo": ("albedo.R", "albedo.G", "albedo.B"),
    "normal": ("normal.X", "normal.Y", "normal.Z"),
    "direct": ("direct.R", "direct.G", "direct.B"),
    "indirect": ("indirect.R", "indirect.G", "indirect.B"),
    "caustic": ("caustic.R", "caustic.G", "caustic.B"),
    "coverage": ("coverage",),
}

# --- Limits, with the reason for each -------------------------------------------------
#: Photons per map: about 150 bytes each with their grids (README, Results), so 5e7
#: photons is ~7.5 GiB; more would not fit the machines this runs on.
MAX_PHOTONS = 50_000_000
#: Fewer global photons leave the cache nothing to gather from.
MIN_GLOBAL_PHOTONS = 1000
#: Fewer photons per estimate than this give estimates so noisy that the cache
#: records' gathers cannot average them away; more than this is a blur, not a lookup.
LOOKUP_SIZE_RANGE = (8, 10_000)
#: Ward's a. Below 0.01 records shrink to the photon spacing and the shifted weight
#: 1/ε − 1/a needs ε < a, finer than the float precision of a record's own position;
#: above 1 a record is extrapolated past the geometry its gather saw (+12 % at a = 10).
MAX_ERROR_RANGE = (0.01, 1.0)
GATHER_RAYS_RANGE = (16, 16_384)
DIRECT_SAMPLES_RANGE = (1, 64)
#: Depths beyond this are unbounded in practice (Russian roulette ends paths long before).
MAX_DEPTH_LIMIT = 1024
#: A max_depth of at least this many segments is read as unbounded where paths meet the
#: cache and the photon maps (:attr:`Settings.bounded`); camera paths still end at
#: max_depth. Photon paths are cut at 64 bounces when unbounded too
#: (photons.MAX_PHOTON_BOUNCES): the light of longer paths is 0.9^64 ≈ 0.1 % of an
#: image whose surfaces reflect 90 %. Read as bounded, the records served one camera
#: depth only and deeper vertices were path-traced: the lamp room at its original
#: max_depth of 65 (Bitterli's scenes ask for 65) had relMSE 2.1 against 0.22
#: unbounded, in 4.9 s against 3.2 s.
UNBOUNDED_FROM = 64
#: A lookup_radius must hold at least this many photons per disc on average (by the
#: requested photon count and the scene's surface area)...
MIN_PHOTONS_PER_LOOKUP = 1.0
#: ...and must be below this fraction of the scene's bounding-box diagonal: a disc
#: larger than the surfaces it sits on undercounts their irradiance.
MAX_RADIUS_DIAGONAL = 0.1


def _fail(name: str, allowed: str, value) -> None:
    raise ValueError(f"integrator 'pmic': parameter '{name}' must be {allowed}, got {value!r}")


def _type_name(value) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string"}.get(type(value),
                                                                           type(value).__name__)


_KIND_NAMES = {int: "integer", float: "float", bool: "boolean", str: "string"}
_KINDS = {"str": str, "int": int, "bool": bool, "float": float, str: str, int: int, bool: bool, float: float}


class _Reader:
    """Reads typed values from Mitsuba ``Properties`` or a plain dict."""

    def __init__(self, props):
        self.props = props

    def get(self, name: str, kind: type, default):
        props = self.props
        if name not in props:
            return default
        value = props[name]
        if kind is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            value = float(value) if ok else value
        else:
            ok = type(value) is kind
        if not ok:
            shown = value if isinstance(value, str) else f"{_type_name(value)} {value!r}"
            _fail(name, f"of type {_KIND_NAMES[kind]}", shown)
        return value


@dataclass(frozen=True)
class Settings:
    """Every user parameter of ``pmic`` (see the class docstring of the integrator)."""

    method: str = "pmic"
    max_depth: int = -1
    rr_depth: int = 5
    hide_emitters: bool = False
    global_photons: int = 200_000
    caustic_photons: int = 100_000
    lookup_size: int = 64
    lookup_radius: float = 0.0
    max_error: float = 0.5
    gather_rays: int = 256
    final_gather: bool = False
    max_photon_paths: int = 0
    direct_samples: int = 4
    guiding: bool = True
    seed: int = 0
    estimator: str = "adaptive"
    aovs: str = ""
    cache_file: str = ""

    @staticmethod
    def parse(props) -> "Settings":
        """Read and check every parameter; raise ValueError naming the first bad
        one."""
        check_names(props)
        reader = _Reader(props)
        defaults = Settings()
        values = {f.name: reader.get(f.name, _KINDS[f.type], getattr(defaults, f.name))
                  for f in fields(Settings)}
        settings = Settings(**values)
        settings.check()
        return settings

    def check(self) -> None:
        def in_range(name, lo, hi, what="an integer"):
            v = getattr(self, name)
            if not (lo <= v <= hi):
                _fail(name, f"{what} in [{lo}, {hi}]", v)

        if self.method not in METHODS:
            _fail("method", f"one of {', '.join(METHODS)}", self.method)
        if not (self.max_depth == -1 or 1 <= self.max_depth <= MAX_DEPTH_LIMIT):
            _fail("max_depth", f"-1 (unbounded) or an integer in [1, {MAX_DEPTH_LIMIT}]", self.max_depth)
        in_range("rr_depth", 1, MAX_DEPTH_LIMIT)
        if not (MIN_GLOBAL_PHOTONS <= self.global_photons <= MAX_PHOTONS):
            _fail("global_photons", f"an integer in [{MIN_GLOBAL_PHOTONS}, {MAX_PHOTONS}] (fewer "
                                    f"cannot estimate indirect light: 0 and 10 gave images 23 % "
                                    f"dark, only direct light)", self.global_photons)
        in_range("caustic_photons", 0, MAX_PHOTONS)
        in_range("lookup_size", *LOOKUP_SIZE_RANGE)
        if not (math.isfinite(self.lookup_radius) and self.lookup_radius >= 0):
            _fail("lookup_radius", "a finite number >= 0 (0: derived from the scene)", self.lookup_radius)
        lo, hi = MAX_ERROR_RANGE
        if not (math.isfinite(self.max_error) and lo <= self.max_error <= hi):
            _fail("max_error", f"a number in [{lo}, {hi}] (below: records finer than float "
                               f"precision; above: records extrapolated past what they saw)",
                  self.max_error)
        in_range("gather_rays", *GATHER_RAYS_RANGE)
        if not (self.max_photon_paths == 0 or MIN_GLOBAL_PHOTONS <= self.max_photon_paths <= 2**40):
            _fail("max_photon_paths", f"0 (automatic) or an integer in [{MIN_GLOBAL_PHOTONS}, 2^40] "
                                      f"(fewer paths cannot fill a usable photon map)",
                  self.max_photon_paths)
        in_range("direct_samples", *DIRECT_SAMPLES_RANGE)
        in_range("seed", 0, 2**32 - 1)
        if self.estimator not in ESTIMATORS:
            _fail("estimator", f"one of {', '.join(ESTIMATORS)}", self.estimator)
        self.aov_list  # noqa: B018 (parses, and refuses an unknown name)

    @property
    def aov_list(self) -> tuple[str, ...]:
        """The AOVs asked for, in :data:`AOVS` order ("all": every one)."""
        asked = [a.strip() for a in self.aovs.split(",") if a.strip()]
        if asked == ["all"]:
            return tuple(AOVS)
        for name in asked:
            if name not in AOVS:
                _fail("aovs", f"a comma-separated list of {', '.join(AOVS)} (or 'all')", self.aovs)
        return tuple(a for a in AOVS if a in asked)

    @property
    def denoiser_guides(self) -> bool:
        """The render outputs a denoiser's guides (``aovs`` holds albedo and normal):
        its image is meant for a denoiser, and the adaptive estimator reads no records
        at first hits (render.config.first_reads)."""
        return "albedo" in self.aov_list and "normal" in self.aov_list

    @property
    def aov_channels(self) -> list[str]:
        return [c for a in self.aov_list for c in AOVS[a]]

    @property
    def final_gather_camera(self) -> bool:
        """Camera paths path-trace their first diffuse bounce and read the cache one
        bounce later (method pmic, estimator final_gather)."""
        return self.method == "pmic" and self.estimator in ("final_gather", "adaptive")

    @property
    def bounded(self) -> bool:
        """Whether ``max_depth`` bounds the paths that the cache and the photon maps
        serve (below :data:`UNBOUNDED_FROM` segments; -1 is unbounded)."""
        return self.max_depth != -1 and self.max_depth < UNBOUNDED_FROM

    @property
    def records_read_depth(self) -> int:
        """The camera depth at which the cache's records (and the precomputed
        irradiance their gather rays read) are read when ``max_depth`` bounds the
        paths: 0 for first-hit interpolation and the classic methods, 1 behind the
        final gather's traced vertex. Their light is that of paths of at most
        max_depth segments read from there; elsewhere the photon map (first hit) or
        more tracing (final gather) serves, depth by depth."""
        return 1 if self.final_gather_camera else 0

    @property
    def gather_strata(self) -> tuple[int, int]:
        """M×N strata of a record's gather (:func:`rays_strata` of ``gather_rays``)."""
        return rays_strata(self.gather_rays)

    #: The parameters the view-independent stages depend on (not hide_emitters,
    #: rr_depth, direct_samples, aovs or cache_file, which only the camera pass reads).
    CACHE_PARAMETERS = ("method", "max_depth", "global_photons", "caustic_photons", "lookup_size",
                        "lookup_radius", "max_error", "gather_rays", "final_gather",
                        "max_photon_paths", "seed", "estimator")

    def key(self) -> tuple:
        """What the view-independent stages depend on, as (name, value) pairs; the
        estimator counts for method ``pmic`` only (its final gather's records hold
        direct light too)."""
        values = {name: getattr(self, name) for name in self.CACHE_PARAMETERS}
        if self.method != "pmic":
            values["estimator"] = "(not used)"
        elif self.estimator == "adaptive":  # (the final gather's cache)
            values["estimator"] = "final_gather"
        return tuple(values.items())


#: Parameters Mitsuba's SamplingIntegrator reads itself (pmic reads hide_emitters too).
MITSUBA_PARAMETERS = ("timeout", "samples_per_pass")


def check_names(props) -> None:
    """Refuse a parameter pmic does not have, suggesting the nearest name (Mitsuba's own
    "unreferenced property" error names it but suggests nothing)."""
    import difflib

    known = [f.name for f in fields(Settings)]
    for name in props.keys():
        if name in known or name in MITSUBA_PARAMETERS:
            continue
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
        hint = f"did you mean '{close[0]}'? " if close else ""
        raise ValueError(f"integrator 'pmic': unknown parameter '{name}' ({hint}pmic's parameters: "
                         f"{', '.join(known)})")


def rays_strata(rays: int) -> tuple[int, int]:
    """M×N strata for about ``rays`` gather rays, N ≈ πM, as Ward & Heckbert recommend."""
    m_theta = max(2, int(round(math.sqrt(rays / math.pi))))
    return m_theta, max(2, rays // m_theta)


def check_against_scene(settings: Settings, surface_area: float, diagonal: float) -> None:
    """Refuse a ``lookup_radius`` that cannot give a correct image in this scene (before
    any photon is traced)."""
    r = settings.lookup_radius
    if r <= 0 or settings.global_photons == 0:
        return
    per_lookup = settings.global_photons * math.pi * r * r / max(surface_area, 1e-30)
    r_min = math.sqrt(MIN_PHOTONS_PER_LOOKUP * surface_area / (math.pi * settings.global_photons))
    r_max = MAX_RADIUS_DIAGONAL * diagonal
    if per_lookup < MIN_PHOTONS_PER_LOOKUP or r > r_max:
        _fail("lookup_radius",
              f"0 (automatic) or, in this scene (diagonal {diagonal:.4g}, surface area "
              f"{surface_area:.4g}, {settings.global_photons} global photons), a radius in "
              f"[{r_min:.4g}, {r_max:.4g}] (smaller holds under {MIN_PHOTONS_PER_LOOKUP:g} photon "
              f"per estimate; larger than {MAX_RADIUS_DIAGONAL:g} of the diagonal undercounts "
              f"the surfaces it covers)", r)
