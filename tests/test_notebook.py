"""The notebooks run end to end in their quick mode (so they cannot rot): the benchmark
results notebook and the one a user copies for their own scene."""
from pathlib import Path

import pytest

nbclient = pytest.importorskip("nbclient")
nbformat = pytest.importorskip("nbformat")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "benchmarks" / "compare_pmic_path.ipynb"
USER_NOTEBOOK = ROOT / "notebooks" / "your_scene.ipynb"


def run_quick(nb, monkeypatch, tmp_path, timeout=600, agg=True):
    """Execute ``nb`` in its quick mode; return its outputs and their printed text.
    ``agg``: matplotlib draws off screen (else the kernel's inline figures)."""
    monkeypatch.setenv("PMIC_NOTEBOOK_QUICK", "1")
    if agg:
        monkeypatch.setenv("MPLBACKEND", "Agg")
    else:
        monkeypatch.delenv("MPLBACKEND", raising=False)
    client = nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    return outputs, "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")


def test_notebook_runs_in_quick_mode(monkeypatch, tmp_path):
    _, text = run_quick(nbformat.read(NOTEBOOK, as_version=4), monkeypatch, tmp_path)
    assert "quick mode" in text and "cornell_box" in text


def test_your_scene_notebook_runs_on_a_bundled_scene(monkeypatch, tmp_path):
    """The notebook a user copies for their own scene, run as shipped (SCENE None: the
    bundled Cornell box) in its small mode: equal-time table, error maps, stages and
    the error-versus-time curve, without an error."""
    monkeypatch.setenv("PMIC_CACHE_DIR", str(tmp_path / "cache"))
    nb = nbformat.read(USER_NOTEBOOK, as_version=4)
    assert nb.cells[1].source.lstrip().startswith("# --- your scene")
    assert "SCENE = None" in nb.cells[1].source
    outputs, text = run_quick(nb, monkeypatch, tmp_path, timeout=900, agg=False)
    assert "cornell_box.xml - path reference, 64 spp" in text
    assert "pmic+OIDN" in text and "path+OIDN" in text and "lower than path's" in text
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 4  # reference, images and error maps, stages, the curve
