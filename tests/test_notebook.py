"""The research notebooks run end to end (reduced sizes) with the public API."""

import json
import os

import numpy as np
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


INVERSE = os.path.join(os.path.dirname(__file__), "..", "notebooks", "inverse.ipynb")


def test_inverse_notebook_runs(tmp_path):
    # the inverse problem at reduced size (6000 steps, 1.8 s of the beam's motion: under
    # one period, but with the ramp's transient): the gradient through simulate matches
    # central differences, and L-BFGS from 30 % off reaches the targets (E within
    # 1 %, alpha within 5 %) from observations with 1 % noise
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("optax")
    nb = nbformat.read(INVERSE, as_version=4)
    sizes = nb.cells[1]
    assert "N_STEPS" in sizes.source and "MAX_ITERS" in sizes.source
    sizes.source = "N_STEPS = 6000\nSAVE_EVERY = 100\nMAX_ITERS = 12"
    nb.cells.append(nbformat.v4.new_code_cell(
        "import json\nprint('RESULT', json.dumps(dict(E_fit=E_fit, alpha_fit=alpha_fit, E0=E0, "
        "ALPHA0=ALPHA0, E_TRUE=E_TRUE, ALPHA_TRUE=ALPHA_TRUE, grad0=np.asarray(grad0).tolist(), "
        "fd=np.asarray(fd).tolist(), loss=history['loss'], iterations=iterations)))"))
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    outputs = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "SUMMARY: E error" in outputs
    result = json.loads(outputs.split("RESULT ", 1)[1].splitlines()[0])
    np.testing.assert_allclose(result["grad0"], result["fd"], rtol=1e-5)
    assert result["loss"][-1] < result["loss"][0] / 100
    E_err = abs(result["E_fit"] / result["E_TRUE"] - 1)
    alpha_err = abs(result["alpha_fit"] / result["ALPHA_TRUE"] - 1)
    assert abs(result["E0"] / result["E_TRUE"] - 1) == pytest.approx(0.3)
    assert abs(result["ALPHA0"] / result["ALPHA_TRUE"] - 1) == pytest.approx(0.3)
    assert E_err < 0.01 and alpha_err < 0.05, (E_err, alpha_err)
    assert 1 <= result["iterations"] <= 12
