"""TOML tables read from dataclasses: the keys a table takes, their kinds and which are
required come from the fields of the class it configures (their type annotations and
defaults), and one catalogue maps the ``[material] model`` names to the laws.

Kinds (the checks of :mod:`jaxsync.app.config`): a field annotated ``float`` (or ``Any``,
the solver's parameters, which may be JAX tracers) takes a TOML number, ``int`` an
integer, ``str`` a string, :data:`TomlPath` a file name (a string resolved against the TOML
file's folder), ``bool`` true or false, ``tuple[float, float, float]`` a list of 3 numbers
and ``tuple[float, ...]`` or ``Sequence[int]`` a non-empty list; ``X | None`` and ``X | Any``
(a value that may also be a JAX array or tracer) take what ``X`` takes. A field without a
default is required.

Some keys of a table are not fields of the class: :class:`DerivedKeys` names them, their
kinds, the fields they stand for and the function that makes those fields' values. The
fibres of :class:`jaxsync.HolzapfelGasserOgden` (``fibres`` is made by
:func:`jaxsync.helical_fibres` from ``fibre_angle`` [degrees], ``fibre_axis`` and
``fibre_origin``, the element centroids of the mesh: :data:`HGO_FIBRES`); the time function
of a load or a prescribed motion (``time``, from ``t_ramp``, ``t_off``, ``period``, ``times``
and ``values``: :data:`TIME_KEYS`); the node set of a ``[[dirichlet]]`` entry (``where``, from
``facet`` or ``plane``: :data:`DIRICHLET_NODES`).

The array tables of loads and boundary conditions are read from their classes the same way
(:data:`BOUNDARY_TABLES`: ``[[dirichlet]]`` from :class:`jaxsync.Dirichlet`, ``[[body_force]]``,
``[[pressure]]`` and ``[[traction]]`` from the loads, ``[[support]]`` from
:class:`jaxsync.ElasticSupport`), and ``[run]`` from :class:`jaxsync.app.config.RunConfig`.

:data:`MATERIAL_MODELS` is the catalogue (an explicit, documented registry):
:func:`register_material_model` adds a law, which is then configurable in a TOML file with
no other change.
"""

from __future__ import annotations

import collections.abc
import dataclasses
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Annotated, Any

import numpy as np

from ..errors import ConfigError

__all__ = ["KeySpec", "DerivedKeys", "TableSchema", "MaterialModel", "MATERIAL_MODELS", "register_material_model",
           "toml_kind", "dataclass_schema", "from_table", "HGO_FIBRES", "DEFAULT_MATERIAL_MODEL", "TomlPath",
           "TIME_KEYS", "DIRICHLET_NODES", "ArrayTable", "BOUNDARY_TABLES", "time_function_of"]

KeySpec = Any
"""A key's kind: ``"number"``, ``"int"``, ``"string"``, ``"path"``, ``"bool"``, ``(kind, n)``
a list of ``n`` entries of that kind (``n`` None: any length >= 1), or a dict ``{key: kind}``
for an inline table."""

TomlPath = Annotated[str, "path"]
"""The annotation of a string field that names a file (TOML kind ``"path"``: a relative path
is taken from the TOML file's folder)."""


def toml_kind(hint) -> KeySpec | None:
    """The TOML kind of a resolved type annotation (module docstring), None: none."""
    if typing.get_origin(hint) is Annotated:
        return "path" if "path" in hint.__metadata__ else toml_kind(typing.get_args(hint)[0])
    if hint is Any or hint is float:
        return "number"
    if hint is bool:
        return "bool"
    if hint is int:
        return "int"
    if hint is str:
        return "string"
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        # None: the key may be left out; Any: the field also takes a JAX array or tracer
        kinds = [toml_kind(a) for a in args if a is not type(None) and a is not Any]
        return kinds[0] if len(kinds) == 1 else None
    if origin in (tuple, list, collections.abc.Sequence) and args:
        if origin is not tuple or (len(args) == 2 and args[1] is Ellipsis):
            kind, n = toml_kind(args[0]), None
        else:
            kinds = {toml_kind(a) for a in args}
            kind, n = (kinds.pop() if len(kinds) == 1 else None), len(args)
        return (kind, n) if isinstance(kind, str) else None
    return None


@dataclasses.dataclass(frozen=True)
class TableSchema:
    """The keys of a table in order, {key: kind}, and those that are required."""

    keys: Mapping[str, KeySpec]
    required: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class DerivedKeys:
    """Keys of a table that are not fields of its class.

    Attributes:
        keys: ``(key, kind, required)`` of each.
        fields: the fields of the class that they stand for (not keys of the table).
        make: ``make(table, mesh) -> {field: value}``, from a checked table (its keys as
            written) and the problem's mesh.
    """

    keys: tuple[tuple[str, KeySpec, bool], ...]
    fields: tuple[str, ...]
    make: Callable[[Mapping[str, Any], Any], dict]


def _derived_groups(derived) -> tuple[DerivedKeys, ...]:
    """``derived`` (None, one :class:`DerivedKeys` or several) as a tuple."""
    if derived is None:
        return ()
    return (derived,) if isinstance(derived, DerivedKeys) else tuple(derived)


def dataclass_schema(cls, *, derived: DerivedKeys | Sequence[DerivedKeys] | None = None, exclude=(),
                     required=()) -> TableSchema:
    """The :class:`TableSchema` of the dataclass ``cls``: its init fields in order (less
    ``exclude`` and those the ``derived`` keys stand for), then the derived keys; the fields
    without a default, the derived keys marked required and ``required`` (keys the table
    needs although the class has a default for them) are required.

    Raises:
        TypeError: a field whose annotation has no TOML kind (exclude it, or give derived keys
            that stand for it).
    """
    hints = typing.get_type_hints(cls, include_extras=True)
    groups = _derived_groups(derived)
    skipped = set(exclude) | {name for group in groups for name in group.fields}
    keys: dict[str, KeySpec] = {}
    needed: list[str] = []
    for field in dataclasses.fields(cls):
        if not field.init or field.name in skipped:
            continue
        kind = toml_kind(hints[field.name])
        if kind is None:
            raise TypeError(f"{cls.__name__}.{field.name}: the annotation {hints[field.name]!r} has no TOML kind "
                            "(float, int, str, bool, tuples of them); exclude it or derive it from other keys")
        keys[field.name] = kind
        if field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            needed.append(field.name)
    for group in groups:
        for key, kind, is_needed in group.keys:
            keys[key] = kind
            if is_needed:
                needed.append(key)
    needed += [key for key in required if key not in needed]
    return TableSchema(keys, tuple(needed))


def _coerced(value, kind: KeySpec):
    """A checked TOML value as the field takes it (numbers as floats, lists as tuples)."""
    if isinstance(kind, tuple):
        return tuple(_coerced(v, kind[0]) for v in value)
    return {"number": float, "int": int, "string": str, "path": str, "bool": bool}[kind](value)


def from_table(cls, table: Mapping[str, Any], schema: TableSchema, extra: Mapping[str, Any] | None = None):
    """An instance of ``cls`` from a checked table: each key of ``schema`` that is a field
    and is given, coerced to its kind, plus ``extra`` fields (the derived ones); fields not
    given keep their defaults."""
    names = {f.name for f in dataclasses.fields(cls) if f.init} - set(extra or {})
    values = {k: _coerced(v, schema.keys[k]) for k, v in table.items() if k in names and k in schema.keys}
    return cls(**values, **dict(extra or {}))


@dataclasses.dataclass(frozen=True)
class MaterialModel:
    """A ``[material] model``: the law's class (a dataclass) and its derived keys, if any."""

    law: type
    derived: DerivedKeys | None = None

    @property
    def schema(self) -> TableSchema:
        """The keys of its ``[material]`` table (besides ``model``)."""
        return dataclass_schema(self.law, derived=self.derived)

    def build(self, table: Mapping[str, Any], mesh):
        """The law of a checked ``[material]`` table on ``mesh``."""
        extra = self.derived.make(table, mesh) if self.derived else None
        return from_table(self.law, table, self.schema, extra)


def _helical_fibres_of(table: Mapping[str, Any], mesh) -> dict:
    from ..fem.materials._hyperelastic import helical_fibres

    centres = mesh.points[mesh.tets].mean(axis=1)
    return {"fibres": helical_fibres(centres, axis=tuple(float(x) for x in table["fibre_axis"]),
                                     angle=float(table["fibre_angle"]),
                                     origin=tuple(float(x) for x in table.get("fibre_origin", (0.0, 0.0, 0.0))))}


HGO_FIBRES = DerivedKeys(keys=(("fibre_angle", "number", True), ("fibre_axis", ("number", 3), True),
                               ("fibre_origin", ("number", 3), False)),
                         fields=("fibres",), make=_helical_fibres_of)
"""The fibre keys of ``model = "holzapfel-gasser-ogden"``: :func:`jaxsync.helical_fibres` of
the element centroids at ``fibre_angle`` degrees around the axis ``fibre_axis`` through
``fibre_origin`` ([0, 0, 0] when not given)."""

_TIME_KEYS = (("t_ramp", "number", False), ("t_off", "number", False), ("period", "number", False),
              ("times", ("number", None), False), ("values", ("number", None), False))


def time_function_of(table: Mapping[str, Any]):
    """The time function of a table's ``t_ramp``, ``t_off``, ``period``, ``times`` and
    ``values``: a ramp to 1 over ``t_ramp`` s (none: 1 from the start), times the periodic
    waveform through (``times``, ``values``) of period ``period`` s, switched off at
    ``t_off`` s; :class:`jaxsync.Constant` when none is given.

    Raises:
        ConfigError: ``times``/``values`` without ``period`` (the waveform would be ignored),
            or ``period`` without both.
    """
    from ..fem._loads import Constant, Periodic, Ramp, StepOff

    t_ramp, t_off = table.get("t_ramp"), table.get("t_off")
    g = Ramp(float(t_ramp)) if t_ramp else Constant()
    if ("times" in table or "values" in table) and "period" not in table:
        raise ConfigError("'times' and 'values' give one period of a waveform: add its 'period' (s); "
                          "without it the waveform would be ignored")
    if "period" in table:
        if "times" not in table or "values" not in table:
            raise ConfigError("a periodic waveform needs 'times' and 'values'")
        wave = Periodic(np.asarray(table["times"], float), np.asarray(table["values"], float),
                        float(table["period"]))
        g = wave if isinstance(g, Constant) else g * wave
    if t_off is not None:
        g = StepOff(float(t_off), g)
    return g


TIME_KEYS = DerivedKeys(keys=_TIME_KEYS, fields=("time",), make=lambda table, mesh: {"time": time_function_of(table)})
"""The ``time`` of a load: :func:`time_function_of` its table (constant when no key is given)."""

HISTORY_KEYS = DerivedKeys(
    keys=_TIME_KEYS, fields=("time",),
    make=lambda table, mesh: {"time": time_function_of(table) if any(k in table for k, _, _ in _TIME_KEYS) else None})
"""The ``time`` of a prescribed motion (:class:`jaxsync.Dirichlet`): :func:`time_function_of`
its table, None (the value at every step) when no key is given."""


def _dirichlet_nodes_of(table: Mapping[str, Any], mesh) -> dict:
    if "facet" in table and "plane" in table:
        raise ConfigError("give one of 'facet' and 'plane', not both (one [[dirichlet]] entry per node set)")
    if "facet" in table:
        return {"where": str(table["facet"])}
    if "plane" not in table:
        raise ConfigError("give 'facet' (a facet-set name) or 'plane' ({ axis = 0, 1 or 2, value = the coordinate })")
    axis, coord = int(table["plane"]["axis"]), float(table["plane"]["value"])
    if axis not in (0, 1, 2):
        raise ConfigError(f"plane axis must be 0, 1, 2 (x, y, z), got {axis}")

    def on_plane(points: np.ndarray, axis=axis, coord=coord) -> np.ndarray:
        tol = 1e-8 * max(float(np.ptp(points[:, axis])), 1.0)
        return np.abs(points[:, axis] - coord) <= tol

    return {"where": on_plane}


DIRICHLET_NODES = DerivedKeys(keys=(("facet", "string", False), ("plane", {"axis": "int", "value": "number"}, False)),
                              fields=("where",), make=_dirichlet_nodes_of)
"""The node set (``where``) of a ``[[dirichlet]]`` entry: the facet set ``facet``, or the nodes on
the plane ``{ axis, value }`` (coordinate ``axis`` equal to ``value`` to 1e-8 of the mesh's
extent); exactly one of them."""


@dataclasses.dataclass(frozen=True)
class ArrayTable:
    """An array of tables ``[[name]]``, one instance of the dataclass ``cls`` per entry.

    Attributes:
        cls: the class of an entry.
        derived: keys that are not fields (:class:`DerivedKeys`).
        required: keys an entry needs although the class has defaults for them.
    """

    cls: type
    derived: tuple[DerivedKeys, ...] = ()
    required: tuple[str, ...] = ()

    @property
    def schema(self) -> TableSchema:
        """Its keys, their kinds and the required ones (:func:`dataclass_schema`)."""
        return dataclass_schema(self.cls, derived=self.derived, required=self.required)

    def build(self, table: Mapping[str, Any], mesh=None):
        """The instance of a checked entry (``mesh``: the problem's, for derived keys that
        need it)."""
        extra: dict = {}
        for group in self.derived:
            extra.update(group.make(table, mesh))
        return from_table(self.cls, table, self.schema, extra)


def _boundary_tables() -> dict[str, ArrayTable]:
    from ..fem._loads import BodyForce, Pressure, Traction
    from ..fem._problem import Dirichlet
    from ..fem.forces._support import ElasticSupport

    return {"dirichlet": ArrayTable(Dirichlet, (DIRICHLET_NODES, HISTORY_KEYS)),
            "body_force": ArrayTable(BodyForce, (TIME_KEYS,), required=("vector",)),
            "pressure": ArrayTable(Pressure, (TIME_KEYS,), required=("surface",)),
            "traction": ArrayTable(Traction, (TIME_KEYS,), required=("surface", "vector")),
            "support": ArrayTable(ElasticSupport, required=("surface",))}


BOUNDARY_TABLES: dict[str, ArrayTable] = _boundary_tables()
"""The array tables of a ``kind = "general"`` problem: ``[[dirichlet]]``, ``[[body_force]]``,
``[[pressure]]``, ``[[traction]]`` and ``[[support]]``, each read from its class (a load's
``surface`` and ``vector`` are required in a file, as the classes' defaults name no facet
set of the user's mesh)."""

DEFAULT_MATERIAL_MODEL = "linear-elastic"
"""The model of a ``[material]`` table without ``model`` (or of a file without one)."""

MATERIAL_MODELS: dict[str, MaterialModel] = {}
"""The catalogue: ``[material] model`` name -> :class:`MaterialModel` (changed only by
:func:`register_material_model`)."""


def register_material_model(name: str, law: type, *, derived: DerivedKeys | None = None,
                            replace: bool = False) -> MaterialModel:
    """Make the dataclass ``law`` configurable as ``[material] model = "<name>"``: its keys,
    their kinds and the required ones come from its fields (:func:`dataclass_schema`), and
    ``derived`` adds keys that are not fields. Returns the catalogue entry.

    Raises:
        ConfigError: a name taken already (pass ``replace=True``), or a class that is not a
            dataclass or has a field without a TOML kind.
    """
    if not dataclasses.is_dataclass(law) or not isinstance(law, type):
        raise ConfigError(f"register_material_model({name!r}, ...): {law!r} is not a dataclass; a material law "
                          "is a (frozen) dataclass whose fields are its parameters")
    if name in MATERIAL_MODELS and not replace:
        raise ConfigError(f"the material model {name!r} is registered already ({MATERIAL_MODELS[name].law.__name__}); "
                          "choose another name, or pass replace=True")
    model = MaterialModel(law, derived)
    try:
        model.schema
    except TypeError as exc:
        raise ConfigError(f"register_material_model({name!r}, {law.__name__}): {exc}") from None
    MATERIAL_MODELS[name] = model
    return model


def _register_builtin_laws() -> None:
    from ..fem.materials._hyperelastic import HolzapfelGasserOgden, NearlyIncompressibleNeoHookean, NeoHookean
    from ..fem.materials._linear_elastic import LinearElastic
    from ..fem.materials._viscoelastic import StandardLinearSolid, ViscoelasticHGO, ViscoelasticNeoHookean

    register_material_model("linear-elastic", LinearElastic)
    register_material_model("neo-hookean", NeoHookean)
    register_material_model("nearly-incompressible-neo-hookean", NearlyIncompressibleNeoHookean)
    register_material_model("holzapfel-gasser-ogden", HolzapfelGasserOgden, derived=HGO_FIBRES)
    register_material_model("standard-linear-solid", StandardLinearSolid)
    register_material_model("viscoelastic-neo-hookean", ViscoelasticNeoHookean)
    register_material_model("viscoelastic-hgo", ViscoelasticHGO, derived=HGO_FIBRES)


_register_builtin_laws()
