import os

import meshio
import numpy as np
import pytest

import jaxsync
from jaxsync import ConfigError
from jaxsync.app.config import RunConfig, default_config_path, load_config, problem_from_config
from jaxsync.cli import main


def write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_relative_paths_are_taken_from_the_toml_folder(tmp_path, monkeypatch):
    case = tmp_path / "cases" / "beam"
    case.mkdir(parents=True)
    mesh = jaxsync.box_beam(3.0, 1.0, 1.0, (3, 1, 1))
    meshio.write_points_cells(str(case / "beam.vtu"), mesh.points, [("tetra", mesh.tets)])
    cfg = write(case / "run.toml", """
[mesh]
file = "beam.vtu"
[run]
output = "out/beam.h5"
xdmf = "beam.xdmf"
checkpoint = "beam.ckpt.h5"
""")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    config = load_config(cfg)
    assert config["mesh"]["file"] == str(case / "beam.vtu")
    problem, run = problem_from_config(config)
    assert problem.mesh.n_elements == mesh.n_elements
    assert run.output == str(case / "out" / "beam.h5")
    assert run.xdmf == str(case / "beam.xdmf")
    assert run.checkpoint == str(case / "beam.ckpt.h5")
    # a relative TOML path: the results stay relative to the cwd, beside the TOML
    monkeypatch.chdir(tmp_path)
    _, run = problem_from_config(load_config(os.path.join("cases", "beam", "run.toml")))
    assert run.output == os.path.join("cases", "beam", "out", "beam.h5")
    # absolute paths are kept
    write(case / "abs.toml", f'[run]\noutput = "{tmp_path / "abs.h5"}"\n')
    assert load_config(case / "abs.toml")["run"]["output"] == str(tmp_path / "abs.h5")


def test_command_line_paths_stay_relative_to_the_cwd(tmp_path, monkeypatch):
    write(tmp_path / "case" / "bar.toml", """
[mesh]
length = 3.0
divisions = [3, 1, 1]
[run]
n_steps = 20
save_every = 10
output = "from_toml.h5"
""")
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "case/bar.toml", "--no-progress"]) == 0
    assert (tmp_path / "case" / "from_toml.h5").exists()
    assert main(["simulate", "case/bar.toml", "-o", "cli.h5", "--no-progress"]) == 0
    assert (tmp_path / "cli.h5").exists() and not (tmp_path / "case" / "cli.h5").exists()


def test_a_mesh_folder_and_the_vtu_series_are_paths_from_the_toml_folder(tmp_path):
    case = tmp_path / "case"
    cfg = write(case / "run.toml", '[mesh]\nfile = "beam-mesh"\n[run]\nvtu = "out/series"\n')
    config = load_config(cfg)
    assert config["mesh"]["file"] == str(case / "beam-mesh")
    assert config["run"]["vtu"] == str(case / "out" / "series")
    del config["mesh"]  # the default beam: no folder to read here
    assert problem_from_config(config)[1].vtu == str(case / "out" / "series")
    assert RunConfig().vtu is None
    write(case / "bad.toml", "[run]\nvtu = 3\n")
    with pytest.raises(ConfigError, match=r"\[run\] vtu = 3 is an integer; expected a path"):
        load_config(case / "bad.toml")


def test_packaged_config_writes_into_the_cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for path in (None, default_config_path()):
        config = load_config(path)
        assert config["run"]["output"] == "cantilever.h5"
        assert "file" not in config.get("mesh", {})


@pytest.mark.parametrize("table, entry, message", [
    ("material", 'E = "6.26e6"',
     r'\[material\] E = "6\.26e6" is a string; expected a number \(int or float\): write E = 6\.26e6'),
    ("material", "nu = true", r"\[material\] nu = true is a boolean; expected a number"),
    ("material", "rho = [1.0]", r"\[material\] rho = \[1\.0\] is a list of 1; expected a number"),
    ("material", "E = nan", r"\[material\] E = nan is not finite"),
    ("problem", "damping = '0.5'", r'\[problem\] damping = "0\.5" is a string'),
    ("problem", "t_off = '3'", r'\[problem\] t_off = "3" is a string'),
    ("problem", 'body_force = [0, "0", -0.5]',
     r'\[problem\] body_force = \[0, "0", -0\.5\] has entry 1 = "0", a string; expected a list of 3 numbers'),
    ("problem", "body_force = [0, -0.5]", r"has 2 entries; expected a list of 3 numbers"),
    ("problem", "kind = 1", r"\[problem\] kind = 1 is an integer; expected a string"),
    ("mesh", "divisions = [25, 1.0, 1]", r"has entry 1 = 1\.0, a float; expected a list of 3 integers"),
    ("mesh", "file = 3", r"\[mesh\] file = 3 is an integer; expected a path"),
    ("mesh", 'length = "25"', r'\[mesh\] length = "25" is a string'),
    ("run", "n_steps = 2e4",
     r"\[run\] n_steps = 20000\.0 is a float; expected an integer: write n_steps = 20000"),
    ("run", 'save_every = "100"', r'\[run\] save_every = "100" is a string; expected an integer'),
    ("run", "checkpoint_every = true", r"checkpoint_every = true is a boolean; expected an integer"),
    ("run", "dt = '2e-4'", r'\[run\] dt = "2e-4" is a string'),
    ("run", "output = 1", r"\[run\] output = 1 is an integer; expected a path"),
    ("run", 'output = ""', r'\[run\] output = "" is empty'),
    ("run", "mass_scaling_beta = '2'", r"mass_scaling_beta = \"2\" is a string"),
    ("run", "mass_scaling_dt = -1e-5", r"mass_scaling_dt = -1e-05 must be positive"),
])
def test_wrong_types_are_refused_with_table_key_value_and_type(tmp_path, table, entry, message):
    cfg = write(tmp_path / "bad.toml", f"[{table}]\n{entry}\n")
    with pytest.raises(ConfigError, match=message) as info:
        load_config(cfg)
    assert str(info.value).startswith(str(cfg))


@pytest.mark.parametrize("text, message", [
    ('[problem]\nkind = "general"\n[[pressure]]\nsurface = "x1"\nmagnitude = "2"\n',
     r'\[\[pressure\]\] #0 magnitude = "2" is a string'),
    ('[problem]\nkind = "general"\n[[pressure]]\nsurface = "x1"\ntimes = [0, "1"]\nvalues = [1, 2]\nperiod = 1\n',
     r"times = \[0, \"1\"\] has entry 1"),
    ('[problem]\nkind = "general"\n[[dirichlet]]\nfacet = 0\n', r"\[\[dirichlet\]\] #0 facet = 0 is an integer"),
    ('[problem]\nkind = "general"\n[[dirichlet]]\nplane = { axis = 0.0, value = 0.0 }\n',
     r"plane = \{ axis = 0\.0, value = 0\.0 \} has axis = 0\.0, a float; expected an inline table"),
    ('[problem]\nkind = "general"\n[[dirichlet]]\nplane = { axis = 0 }\n', r"lacks value"),
    ('[problem]\nkind = "general"\n[[dirichlet]]\nfacet = "x0"\ncomponents = [0, "1"]\n',
     r"components = \[0, \"1\"\] has entry 1"),
    ('[problem]\nkind = "general"\n[[body_force]]\nvector = "0 0 1"\n',
     r'vector = "0 0 1" is a string; expected a list of 3 numbers'),
    ('[pressure]\nsurface = "x1"\n', r"must be an array of tables: write each entry under its own \[\[pressure\]\]"),
    ('mesh = 3\n', r"'mesh' must be a table"),
    ('[run]\nmass_scaling_dt = 1e-5\nmass_scaling_beta = 2.0\n',
     r"both mass_scaling_dt and mass_scaling_beta; give only one"),
])
def test_wrong_types_in_arrays_of_tables_and_structure(tmp_path, text, message):
    cfg = write(tmp_path / "bad.toml", text)
    with pytest.raises(ConfigError, match=message):
        load_config(cfg)


def test_python_dictionaries_are_checked_too():
    with pytest.raises(ConfigError, match=r'\[material\] E = "6\.26e6" is a string'):
        problem_from_config({"material": {"E": "6.26e6"}})
    with pytest.raises(ConfigError, match="only one of mass_scaling_dt"):
        problem_from_config({}, mass_scaling_dt=1e-4, mass_scaling_beta=2.0)
    with pytest.raises(ConfigError, match="mass_scaling_beta must be a positive number"):
        problem_from_config({}, mass_scaling_beta=-2.0)


def test_numbers_of_both_kinds_are_accepted_and_mass_scaling_is_applied(tmp_path):
    cfg = write(tmp_path / "ok.toml", """
[mesh]
length = 4
divisions = [4, 1, 1]
[material]
E = 1000000
nu = 0.3
rho = 1
[problem]
body_force = [0, 0, -1]
t_ramp = 1
[run]
n_steps = 100
save_every = 10
dt = 1e-4
checkpoint_every = 50
mass_scaling_dt = 5e-4
""")
    reference = jaxsync.cantilever(jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1)),
                                   body_force=(0.0, 0.0, -1.0))
    with pytest.warns(jaxsync.MassScalingWarning, match="dt_hat=5.0000e-04 s"):
        problem, run = problem_from_config(load_config(cfg))
    expected, percent = jaxsync.mass_scaling(reference, dt_target=5e-4, warn_above_percent=None)
    assert run == RunConfig(n_steps=100, save_every=10, dt=1e-4, output="trajectory.h5",  # default: the cwd
                            checkpoint_every=50, mass_scaling_dt=5e-4, added_mass_percent=percent)
    np.testing.assert_array_equal(problem.density_scale, expected.density_scale)
    assert problem.dt == pytest.approx(5e-4, rel=1e-12)
    # an override replaces the file's mass scaling
    _, run = problem_from_config(load_config(cfg), mass_scaling_beta=1.0)
    assert run.mass_scaling_dt is None and run.added_mass_percent == 0.0


GENERAL = ('[mesh]\nlength = 4.0\ndivisions = [4, 1, 1]\n[problem]\nkind = "general"\n'
           '[[dirichlet]]\nfacet = "x0"\n')


@pytest.mark.parametrize("extra, message", [
    # a waveform's samples without its period would be dropped: the load would be constant
    ('[[pressure]]\nsurface = "x1"\ntimes = [0.0, 0.05]\nvalues = [1.0, 2.0]\n', "add its 'period'"),
    ('[[dirichlet]]\nfacet = "x1"\nplane = { axis = 0, value = 4.0 }\n', "one of 'facet' and 'plane', not both"),
    ('[[body_force]]\nvector = [0.0, 0.0, -1.0]\nt_off = -2.0\n', r"StepOff\.t_off must be positive"),
])
def test_configurations_that_would_do_something_else_than_written_are_refused(tmp_path, extra, message):
    path = write(tmp_path / "p.toml", GENERAL + extra)
    with pytest.raises((ConfigError, jaxsync.ProblemError), match=message):
        problem_from_config(load_config(path))


def test_cantilever_keys_in_a_general_problem_are_refused(tmp_path):
    text = GENERAL.replace('kind = "general"\n', 'kind = "general"\nbody_force = [0.0, 0.0, -1.0]\nt_ramp = 1.0\n')
    with pytest.raises(ConfigError, match=r"\[problem\] body_force, t_ramp: only used with kind = \"cantilever\""):
        problem_from_config(load_config(write(tmp_path / "p.toml", text)))
