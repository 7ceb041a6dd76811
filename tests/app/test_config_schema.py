"""The TOML schema read from the dataclasses (jaxsync.app.config_schema): for every law of
the catalogue, a [material] table written from its fields loads into the instance built
directly; unknown and missing keys name themselves; a law registered here is configurable
with no other change; [[support]] from ElasticSupport."""

from __future__ import annotations

import dataclasses
import re
import typing
from typing import Any

import numpy as np
import pytest

import jaxsync
from jaxsync.app.config import RunConfig, load_config, problem_from_config
from jaxsync.app.config_schema import (
    BOUNDARY_TABLES,
    MATERIAL_MODELS,
    TIME_KEYS,
    ArrayTable,
    TomlPath,
    dataclass_schema,
    register_material_model,
    toml_kind,
)
from jaxsync.errors import ConfigError
from jaxsync.pytree import pytree_dataclass, static_field

BEAM = "[mesh]\nlength = 4.0\ndivisions = [4, 1, 1]\n"


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def _value(kind, default):
    """A valid value of a key other than its default (so that reading it is seen)."""
    if isinstance(kind, tuple):
        entry, n = kind
        return tuple(_value(entry, None) for _ in range(n or 2))
    if kind == "number":
        return 2.0 if default in (None, dataclasses.MISSING) else (0.1 if default == 0 else 1.1 * float(default))
    return {"int": 3, "string": "name", "bool": True}[kind]


def _fields_table(law, derived_values=None):
    """{key: value} of every init field of ``law`` (read here from the dataclass itself)."""
    hints = typing.get_type_hints(law)
    table = {}
    for field in dataclasses.fields(law):
        if field.init and field.name in {"fibres"} | set(derived_values or {}):
            continue
        kind = toml_kind(hints[field.name])
        table[field.name] = _value(kind, field.default)
    return table


HGO_DERIVED = {"fibre_angle": 29.0, "fibre_axis": (1.0, 0.0, 0.0), "fibre_origin": (0.0, 0.5, 0.5)}


def _load_material(tmp_path, model, table):
    cfg = tmp_path / f"{model}.toml"
    cfg.write_text(BEAM + "[material]\n" + f'model = "{model}"\n'
                   + "".join(f"{k} = {_toml(v)}\n" for k, v in table.items()))
    return problem_from_config(load_config(cfg))[0].material


@pytest.mark.parametrize("model", sorted(MATERIAL_MODELS))
def test_every_law_of_the_catalogue_loads_as_built_directly(tmp_path, model):
    law = MATERIAL_MODELS[model].law
    derived = HGO_DERIVED if MATERIAL_MODELS[model].derived is not None else {}  # the HGO fibre keys
    # away from incompressibility (no locking warning on P1): nu 0.35, K = 3 mu
    fields = {k: {"nu": 0.35, "kappa_bulk": 6.0}.get(k, v) for k, v in _fields_table(law).items()}
    loaded = _load_material(tmp_path, model, {**fields, **derived})
    direct = law(**fields)
    assert type(loaded) is law
    for name, value in fields.items():
        assert getattr(loaded, name) == getattr(direct, name) == value, name
    if derived:
        mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
        fibres = jaxsync.helical_fibres(mesh.points[mesh.tets].mean(axis=1), axis=(1.0, 0.0, 0.0), angle=29.0,
                                        origin=(0.0, 0.5, 0.5))
        np.testing.assert_array_equal(loaded.fibres, fibres)
    else:
        assert loaded == direct


def test_the_builtin_schemas_are_the_fields():
    """Exactly the keys the files have always had, in the order the messages list them."""
    keys = {name: (tuple(m.schema.keys), m.schema.required) for name, m in MATERIAL_MODELS.items()}
    assert keys["linear-elastic"] == (("E", "nu", "rho"), ())
    assert keys["neo-hookean"] == keys["nearly-incompressible-neo-hookean"] == (("E", "nu", "rho"), ())
    assert keys["holzapfel-gasser-ogden"] == (
        ("mu", "k1", "k2", "kappa_bulk", "rho", "dispersion", "fibre_angle", "fibre_axis", "fibre_origin"),
        ("mu", "k1", "k2", "kappa_bulk", "fibre_angle", "fibre_axis"))
    assert MATERIAL_MODELS["holzapfel-gasser-ogden"].schema.keys["fibre_axis"] == ("number", 3)


@pytest.mark.parametrize("model", sorted(MATERIAL_MODELS))
def test_an_unknown_key_and_each_missing_required_key_are_named(tmp_path, model):
    schema = MATERIAL_MODELS[model].schema
    table = {k: _value(kind, None) for k, kind in schema.keys.items() if k in schema.required}
    cfg = tmp_path / "bad.toml"
    cfg.write_text(BEAM + f'[material]\nmodel = "{model}"\nstiffnes = 1.0\n')
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['stiffnes'\] in \[material\]"):
        load_config(cfg)
    for missing in schema.required:
        cfg.write_text(BEAM + f'[material]\nmodel = "{model}"\n'
                       + "".join(f"{k} = {_toml(v)}\n" for k, v in table.items() if k != missing))
        with pytest.raises(ConfigError, match=rf'model = "{model}" needs {missing};'):
            load_config(cfg)


def test_a_wrong_kind_names_the_key(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(BEAM + '[material]\nmodel = "holzapfel-gasser-ogden"\nmu = 1.0\nk1 = 1.0\nk2 = 1.0\n'
                   'kappa_bulk = 1.0\nfibre_angle = 30.0\nfibre_axis = [1.0, 0.0]\n')
    with pytest.raises(ConfigError, match=r"\[material\] fibre_axis = \[1.0, 0.0\] has 2 entries; expected a list "
                                          "of 3 numbers"):
        load_config(cfg)


@pytest.mark.parametrize("hint, kind", [
    (float, "number"), (Any, "number"), (int, "int"), (str, "string"), (bool, "bool"),
    (float | None, "number"), (tuple[float, float, float], ("number", 3)), (tuple[int, ...], ("int", None)),
    (list[str], ("string", None)), (np.ndarray, None), (dict, None), (tuple[float, str], None),
    # a field that may also hold a JAX array or tracer takes what its plain type takes
    (tuple[float, float, float] | Any, ("number", 3)), (float | Any, "number"),
    (typing.Sequence[int], ("int", None)), (TomlPath, "path"), (TomlPath | None, "path"), (str | Any | int, None),
])
def test_toml_kinds_of_annotations(hint, kind):
    assert toml_kind(hint) == kind


@pytest.fixture
def tagged_law():
    """A law defined here (LinearElastic with three more fields), registered for the test."""

    @pytree_dataclass
    class TaggedElastic(jaxsync.LinearElastic):
        layers: int = static_field(default=1)
        label: str = static_field(default="wall")
        stretch: tuple[float, float, float] = static_field(default=(1.0, 1.0, 1.0))

    register_material_model("tagged-elastic", TaggedElastic)
    yield TaggedElastic
    del MATERIAL_MODELS["tagged-elastic"]


def test_a_law_registered_here_is_configurable_with_no_other_change(tmp_path, tagged_law):
    loaded = _load_material(tmp_path, "tagged-elastic", {"E": 2.0e6, "layers": 3, "label": "media",
                                                         "stretch": [1.0, 1.1, 1.2]})
    assert loaded == tagged_law(E=2.0e6, layers=3, label="media", stretch=(1.0, 1.1, 1.2))
    assert _load_material(tmp_path, "tagged-elastic", {}) == tagged_law()
    cfg = tmp_path / "bad.toml"
    cfg.write_text(BEAM + '[material]\nmodel = "tagged-elastic"\nlayers = 2.5\n')
    with pytest.raises(ConfigError, match=r"\[material\] layers = 2.5 is a float; expected an integer"):
        load_config(cfg)
    cfg.write_text(BEAM + '[material]\nmodel = "tagged-elastic"\nk1 = 1.0\n')
    with pytest.raises(ConfigError, match=re.escape('key(s) k1 are not parameters of model = "tagged-elastic"; '
                                                    "its keys: model, E, nu, rho, layers, label, stretch")):
        load_config(cfg)
    cfg.write_text(BEAM + '[material]\nmodel = "rubber"\n')
    with pytest.raises(ConfigError, match='allowed: "linear-elastic", .*"tagged-elastic"'):
        load_config(cfg)


def test_registration_refuses_what_cannot_be_configured(tagged_law):
    with pytest.raises(ConfigError, match="'tagged-elastic' is registered already"):
        register_material_model("tagged-elastic", jaxsync.LinearElastic)
    with pytest.raises(ConfigError, match="is not a dataclass"):
        register_material_model("plain", object)

    @dataclasses.dataclass(frozen=True)
    class WithArray:
        E: float = 1.0
        table: np.ndarray = None

    with pytest.raises(ConfigError, match=r"WithArray.table: the annotation .* has no TOML kind"):
        register_material_model("with-array", WithArray)
    assert "with-array" not in MATERIAL_MODELS and "plain" not in MATERIAL_MODELS


def test_support_tables_are_the_fields_of_elastic_support(tmp_path):
    schema = dataclass_schema(jaxsync.ElasticSupport)
    assert dict(schema.keys) == {"stiffness": "number", "damping": "number", "surface": "string",
                                 "normal_only": "bool"}
    assert schema.required == ("stiffness",)
    cfg = tmp_path / "support.toml"
    cfg.write_text(BEAM + '[problem]\nkind = "general"\n[[dirichlet]]\nfacet = "x0"\n'
                   '[[support]]\nsurface = "x1"\nstiffness = 2.0e3\ndamping = 10.0\nnormal_only = true\n')
    problem, _ = problem_from_config(load_config(cfg))
    assert problem.supports == (jaxsync.ElasticSupport(2.0e3, 10.0, surface="x1", normal_only=True),)
    cfg.write_text(BEAM + '[problem]\nkind = "general"\n[[support]]\nsurface = "x1"\nstiffness = 1.0\nspring = 2\n')
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['spring'\] in \[\[support\]\] #0"):
        load_config(cfg)


TIME_KEY_NAMES = ("t_ramp", "t_off", "period", "times", "values")


@pytest.mark.parametrize("name, cls, derived", [
    ("dirichlet", jaxsync.Dirichlet, {"where": ("facet", "plane"), "time": TIME_KEY_NAMES}),
    ("body_force", jaxsync.BodyForce, {"time": TIME_KEY_NAMES}),
    ("pressure", jaxsync.Pressure, {"time": TIME_KEY_NAMES}),
    ("traction", jaxsync.Traction, {"time": TIME_KEY_NAMES}),
    ("support", jaxsync.ElasticSupport, {}),
])
def test_each_boundary_table_is_the_fields_of_its_class(name, cls, derived):
    """The keys of [[name]] are the init fields of the class (read here from the dataclass),
    less those that derived keys stand for, then the derived keys; nothing else."""
    table = BOUNDARY_TABLES[name]
    assert table.cls is cls
    fields = [f.name for f in dataclasses.fields(cls) if f.init]
    assert set(derived) <= set(fields)
    expected = [f for f in fields if f not in derived] + [k for keys in derived.values() for k in keys]
    assert list(table.schema.keys) == expected
    # a field without a default is required in a file too (Dirichlet.where: one of facet and plane)
    needed = {f.name for f in dataclasses.fields(cls) if f.init and f.name not in derived
              and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
    assert needed <= set(table.schema.required)


def test_a_field_added_to_a_load_is_a_key_with_no_other_change():
    @pytree_dataclass
    class ScaledPressure(jaxsync.Pressure):
        scale: float = static_field(default=1.0)
        tag: str = static_field(default="x")

    table = ArrayTable(ScaledPressure, (TIME_KEYS,), required=("surface",))
    assert table.schema.keys["scale"] == "number" and table.schema.keys["tag"] == "string"
    load = table.build({"surface": "x1", "magnitude": 3.0, "scale": 2, "tag": "lumen", "t_ramp": 0.5})
    assert load == ScaledPressure(3.0, jaxsync.Ramp(0.5), surface="x1", scale=2.0, tag="lumen")


def test_loads_and_motions_from_a_file_equal_those_built_directly(tmp_path):
    """Every load kind with each form of time function, and a plane Dirichlet with a history:
    the problem read from the file has the loads and conditions built here with the classes
    (the time functions evaluated at many times, the plane's nodes found from the coordinates)."""
    cfg = tmp_path / "general.toml"
    cfg.write_text(
        BEAM + '[problem]\nkind = "general"\n'
        '[[dirichlet]]\nfacet = "x0"\n'
        '[[dirichlet]]\nplane = { axis = 0, value = 4.0 }\nvalue = [0.0, 0.1, 0.0]\ncomponents = [1]\n'
        't_ramp = 0.2\n'
        '[[body_force]]\nvector = [0.0, 0.0, -2.0]\nperiod = 0.5\ntimes = [0.0, 0.25]\nvalues = [1.0, 3.0]\n'
        '[[pressure]]\nsurface = "x1"\ntimes = [0.0, 0.1, 0.3]\nvalues = [10.0, 16.0, 12.0]\nperiod = 0.4\n'
        't_ramp = 0.1\nt_off = 2.0\n'
        '[[traction]]\nsurface = "y0"\nvector = [1.0, 0.0, 0.0]\nt_off = 0.7\n')
    problem, _ = problem_from_config(load_config(cfg))
    wave = jaxsync.Periodic(np.array([0.0, 0.1, 0.3]), np.array([10.0, 16.0, 12.0]), 0.4)
    body, pressure, traction = problem.loads
    expected = (jaxsync.BodyForce((0.0, 0.0, -2.0), jaxsync.Periodic(np.array([0.0, 0.25]), np.array([1.0, 3.0]), 0.5)),
                jaxsync.Pressure(1.0, jaxsync.StepOff(2.0, jaxsync.Ramp(0.1) * wave), surface="x1"),
                jaxsync.Traction((1.0, 0.0, 0.0), jaxsync.StepOff(0.7, jaxsync.Constant()), surface="y0"))
    t = np.linspace(0.0, 2.5, 251)
    for loaded, direct in zip((body, pressure, traction), expected):
        assert type(loaded) is type(direct)
        for f in dataclasses.fields(direct):
            if f.name != "time":
                np.testing.assert_array_equal(getattr(loaded, f.name), getattr(direct, f.name))
        np.testing.assert_array_equal([float(loaded.time(s)) for s in t], [float(direct.time(s)) for s in t])
    assert pressure.magnitude == 1.0  # the waveform's values are the pressure
    clamp, plane = problem.dirichlet
    assert clamp.where == "x0" and clamp.time is None
    assert plane.value == (0.0, 0.1, 0.0) and plane.components == (1,)
    on_plane = np.flatnonzero(np.isclose(problem.space.points[:, 0], 4.0))
    np.testing.assert_array_equal(plane.nodes(problem.space), on_plane)
    np.testing.assert_array_equal([float(plane.time(s)) for s in t], [float(jaxsync.Ramp(0.2)(s)) for s in t])


@pytest.mark.parametrize("table, missing", [
    ('[[traction]]\nsurface = "x1"\n', "vector"),
    ('[[pressure]]\nmagnitude = 2.0\n', "surface"),
    ('[[body_force]]\nt_ramp = 1.0\n', "vector"),
    ('[[support]]\nstiffness = 1.0\n', "surface"),
    ('[[support]]\nsurface = "x1"\n', "stiffness"),
])
def test_a_missing_key_of_a_boundary_table_is_named_when_the_file_is_read(tmp_path, table, missing):
    cfg = tmp_path / "missing.toml"
    cfg.write_text(BEAM + '[problem]\nkind = "general"\n' + table)
    name = table.split("]]")[0].lstrip("[")
    with pytest.raises(ConfigError, match=rf"\[\[{name}\]\] #0 needs {missing}; its keys: "):
        load_config(cfg)


def test_a_dirichlet_entry_names_its_node_set_once(tmp_path):
    cfg = tmp_path / "nodes.toml"
    for body, message in (('value = [0.0, 0.0, 0.0]\n', r"\[\[dirichlet\]\] #0: give 'facet'"),
                          ('plane = { axis = 3, value = 0.0 }\n', r"\[\[dirichlet\]\] #0: plane axis must be 0, 1, 2"),
                          ('facet = "x0"\ntimes = [0.0, 1.0]\nvalues = [0.0, 1.0]\n', "add its 'period'")):
        cfg.write_text(BEAM + '[problem]\nkind = "general"\n[[dirichlet]]\n' + body)
        with pytest.raises(ConfigError, match=message):
            problem_from_config(load_config(cfg))


def test_the_run_table_is_the_fields_of_run_config(tmp_path):
    schema = dataclass_schema(RunConfig, exclude=("added_mass_percent",))
    fields = [f.name for f in dataclasses.fields(RunConfig) if f.name != "added_mass_percent"]
    assert list(schema.keys) == fields and schema.required == ()
    # the file names are paths: relative ones are taken from the file's folder
    assert {k for k, kind in schema.keys.items() if kind == "path"} == {"output", "xdmf", "vtu", "checkpoint"}
    (tmp_path / "case").mkdir()
    cfg = tmp_path / "case" / "run.toml"
    cfg.write_text(BEAM + '[run]\nn_steps = 10\noutput = "out.h5"\nvtu = "series"\ncheckpoint = "c.h5"\n')
    _, run = problem_from_config(load_config(cfg))
    assert run.n_steps == 10
    folder = tmp_path / "case"
    assert (run.output, run.vtu, run.checkpoint) == tuple(str(folder / f) for f in ("out.h5", "series", "c.h5"))
