"""TOML tables read from dataclasses: the keys a table takes, their kinds and which are
required come from the fields of the class it configures (their type annotations and
defaults), and one catalogue maps the ``[material] model`` names to the laws.

Kinds (the checks of :mod:`jaxsync.app.config`): a field annotated ``float`` (or ``Any``,
the solver's parameters, which may be JAX tracers) takes a TOML number, ``int`` an
integer, ``str`` a string, ``bool`` true or false, ``tuple[float, float, float]`` a list of
3 numbers and ``tuple[float, ...]`` a non-empty list; ``X | None`` takes what ``X`` takes. A
field without a default is required.

Some keys of a table are not fields of the class: :class:`DerivedKeys` names them, their
kinds, the fields they stand for and the function that makes those fields' values. The one
such table of the built-in laws: the fibres of :class:`jaxsync.HolzapfelGasserOgden`
(``fibres`` is made by :func:`jaxsync.helical_fibres` from ``fibre_angle`` [degrees],
``fibre_axis`` and ``fibre_origin``, the element centroids of the mesh).

:data:`MATERIAL_MODELS` is the catalogue (an explicit, documented registry):
:func:`register_material_model` adds a law, which is then configurable in a TOML file with
no other change.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any

from ..errors import ConfigError

__all__ = ["KeySpec", "DerivedKeys", "TableSchema", "MaterialModel", "MATERIAL_MODELS", "register_material_model",
           "toml_kind", "dataclass_schema", "from_table", "HGO_FIBRES", "DEFAULT_MATERIAL_MODEL"]

KeySpec = Any
"""A key's kind: ``"number"``, ``"int"``, ``"string"``, ``"bool"``, or ``(kind, n)`` a list of
``n`` entries of that kind (``n`` None: any length >= 1)."""


def toml_kind(hint) -> KeySpec | None:
    """The TOML kind of a resolved type annotation (module docstring), None: none."""
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
        kinds = [toml_kind(a) for a in args if a is not type(None)]
        return kinds[0] if len(kinds) == 1 else None
    if origin in (tuple, list) and args:
        if origin is list or (len(args) == 2 and args[1] is Ellipsis):
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


def dataclass_schema(cls, *, derived: DerivedKeys | None = None, exclude=()) -> TableSchema:
    """The :class:`TableSchema` of the dataclass ``cls``: its init fields in order (less
    ``exclude`` and those ``derived`` stands for), then the derived keys.

    Raises:
        TypeError: a field whose annotation has no TOML kind (exclude it, or give derived keys
            that stand for it).
    """
    hints = typing.get_type_hints(cls)
    skipped = set(exclude) | set(derived.fields if derived else ())
    keys: dict[str, KeySpec] = {}
    required: list[str] = []
    for field in dataclasses.fields(cls):
        if not field.init or field.name in skipped:
            continue
        kind = toml_kind(hints[field.name])
        if kind is None:
            raise TypeError(f"{cls.__name__}.{field.name}: the annotation {hints[field.name]!r} has no TOML kind "
                            "(float, int, str, bool, tuples of them); exclude it or derive it from other keys")
        keys[field.name] = kind
        if field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            required.append(field.name)
    for key, kind, needed in (derived.keys if derived else ()):
        keys[key] = kind
        if needed:
            required.append(key)
    return TableSchema(keys, tuple(required))


def _coerced(value, kind: KeySpec):
    """A checked TOML value as the field takes it (numbers as floats, lists as tuples)."""
    if isinstance(kind, tuple):
        return tuple(_coerced(v, kind[0]) for v in value)
    return {"number": float, "int": int, "string": str, "bool": bool}[kind](value)


def from_table(cls, table: Mapping[str, Any], schema: TableSchema, extra: Mapping[str, Any] | None = None):
    """An instance of ``cls`` from a checked table: each key of ``schema`` that is a field
    and is given, coerced to its kind, plus ``extra`` fields (the derived ones); fields not
    given keep their defaults."""
    names = {f.name for f in dataclasses.fields(cls) if f.init}
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
    from ..fem.hyperelastic import helical_fibres

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
    from ..fem.hyperelastic import HolzapfelGasserOgden, NearlyIncompressibleNeoHookean, NeoHookean
    from ..fem.material import LinearElastic
    from ..fem.viscoelastic import StandardLinearSolid, ViscoelasticHGO, ViscoelasticNeoHookean

    register_material_model("linear-elastic", LinearElastic)
    register_material_model("neo-hookean", NeoHookean)
    register_material_model("nearly-incompressible-neo-hookean", NearlyIncompressibleNeoHookean)
    register_material_model("holzapfel-gasser-ogden", HolzapfelGasserOgden, derived=HGO_FIBRES)
    register_material_model("standard-linear-solid", StandardLinearSolid)
    register_material_model("viscoelastic-neo-hookean", ViscoelasticNeoHookean)
    register_material_model("viscoelastic-hgo", ViscoelasticHGO, derived=HGO_FIBRES)


_register_builtin_laws()
