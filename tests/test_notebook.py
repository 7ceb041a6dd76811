"""The research notebook runs end to end (reduced sizes) with the public API."""

import os

import pytest

NOTEBOOK = os.path.join(os.path.dirname(__file__), "..", "notebooks", "cantilever.ipynb")


def test_cantilever_notebook_runs(tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    sizes = nb.cells[1]
    assert "N_STEPS" in sizes.source
    sizes.source = "N_STEPS = 1200\nN_S, N_P, N_F = 5, 5, 5\nHIDDEN, EPOCHS = 8, 2"
    env_flags = os.environ.get("XLA_FLAGS", "")
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    assert (tmp_path / "cantilever_surrogate.h5").exists()
    outputs = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "es_hat at the end" in outputs
    assert env_flags == os.environ.get("XLA_FLAGS", "")
