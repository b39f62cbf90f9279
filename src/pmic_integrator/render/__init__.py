"""Stage 4, the render: camera paths that read what stages 1-3 prepared.

- :mod:`.config`: the per-render switches (:class:`~.config.PathConfig`) and what the
  paths read (:class:`~.config.PathContext`);
- :mod:`.state`: the loop state (:class:`~.state.PathState`);
- :mod:`.path`: the camera loop, one vertex a sequence of named strategies;
- :mod:`.vertex`: the surface met and what is decided there;
- :mod:`.reads`: where a vertex reads indirect light and where it is traced;
- :mod:`.estimators`: the reads themselves (cache, photon maps, precomputed irradiance);
- :mod:`.direct`: direct light (emission met, emitter samples, coats, delta lights);
- :mod:`.continuation`: guiding, lobe splits, roulettes, the next vertex;
- :mod:`.caustics`: caustic-map reads deferred past the loop.

The BSDF cases both this path and the gather walk read are in :mod:`pmic_integrator.cases`.
"""
