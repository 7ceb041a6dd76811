"""The surrogate models by name: the one registry of model kinds.

A surrogate file names the model it holds by its ``kind`` (``"lstm"``, ``"linear"``, or a
model a user registered), and so do :class:`~jaxsync.surrogate.ArchitectureChoice`
(``model=``) and ``jaxsync train --model``. This module maps that string to the model's
class (a :class:`~jaxsync.surrogate.models.SurrogateArchitecture`):

=========  =====================================================
kind       class
=========  =====================================================
"lstm"     :class:`~jaxsync.surrogate.models.LSTMArchitecture`
"linear"   :class:`~jaxsync.surrogate.models.LinearArchitecture`
=========  =====================================================

:func:`register_surrogate` adds a model (its class attribute ``kind`` is its name;
:func:`unregister_surrogate` removes it again); a model
must be registered before a file of its kind is loaded or ``jaxsync train --model`` names
it (the command line's parser lists the kinds registered when it is built). The registry
is the only global state of the surrogate package: a dictionary filled by the built-in
models (imported on first lookup, so that naming a kind imports no numerical library) and
by :func:`register_surrogate`.
"""

from __future__ import annotations

import importlib

from jaxsync.errors import ConfigError

__all__ = ["register_surrogate", "unregister_surrogate", "surrogate_class", "surrogate_kinds", "BUILTIN_SURROGATES"]

#: kind -> (module, class name) of the built-in models, imported on first lookup
BUILTIN_SURROGATES: dict[str, tuple[str, str]] = {
    "lstm": ("jaxsync.surrogate.models._lstm", "LSTMArchitecture"),
    "linear": ("jaxsync.surrogate.models._linear", "LinearArchitecture"),
}

# the methods of the protocol (jaxsync.surrogate.models) every registered class has
_PROTOCOL = ("init", "forward", "init_replicas", "loss", "fit", "online_update", "prediction_cost", "to_dict",
             "from_dict", "from_choice", "check_choice", "candidates_per_part", "summary_fields", "fit_description")

# kind -> class of the models registered by register_surrogate (and the built-ins, once looked up)
_REGISTERED: dict[str, type] = {}


def register_surrogate(cls: type, *, replace: bool = False) -> type:
    """Register the surrogate model ``cls`` under its ``cls.kind`` (usable as a class
    decorator): surrogate files of that kind then load, and
    ``ArchitectureChoice(model=cls.kind)`` and ``jaxsync train --model`` train it.

    Args:
        cls: a subclass of :class:`~jaxsync.surrogate.models.SurrogateArchitecture`
            (through :class:`~jaxsync.surrogate.models.GradientFitted` or
            :class:`~jaxsync.surrogate.models.LeastSquaresFitted`) with a class attribute
            ``kind``, a non-empty string.
        replace: allow a kind already registered to name ``cls`` from now on (a built-in
            kind is never replaced).

    Returns:
        ``cls``.

    Raises:
        ConfigError: not a surrogate model, no ``kind``, or a kind taken by another class.
    """
    # the protocol's methods, checked by name: this module imports no model (nor JAX)
    missing = [name for name in _PROTOCOL if not callable(getattr(cls, name, None))] if isinstance(cls, type) else 0
    if missing != []:
        raise ConfigError(f"register_surrogate takes a subclass of jaxsync.surrogate.SurrogateArchitecture "
                          f"(GradientFitted or LeastSquaresFitted), got {cls!r}"
                          + (f", which lacks {', '.join(missing)}" if missing else ""))
    kind = getattr(cls, "kind", None)
    if not isinstance(kind, str) or not kind or kind != kind.strip():
        raise ConfigError(f"{cls.__name__}.kind must be a non-empty string without surrounding blanks (the name "
                          f"surrogate files and --model use), got {kind!r}")
    if kind in BUILTIN_SURROGATES and surrogate_class(kind) is not cls:
        raise ConfigError(f"the surrogate kind {kind!r} is built in; give {cls.__name__} another kind")
    taken = _REGISTERED.get(kind)
    if taken is not None and taken is not cls and not replace:
        raise ConfigError(f"the surrogate kind {kind!r} is registered to {taken.__module__}.{taken.__qualname__}; "
                          f"give {cls.__name__} another kind, or pass replace=True")
    _REGISTERED[kind] = cls
    return cls


def unregister_surrogate(kind: str) -> type:
    """Remove the model registered under ``kind`` (e.g. at the end of a test); returns its
    class. Its files no longer load until it is registered again.

    Raises:
        ConfigError: ``kind`` is built in, or no model of that kind is registered.
    """
    if kind in BUILTIN_SURROGATES:
        raise ConfigError(f"the surrogate kind {kind!r} is built in and cannot be unregistered")
    if kind not in _REGISTERED:
        raise ConfigError(f"no surrogate model of kind {kind!r} is registered; the registered kinds are "
                          f"{', '.join(map(repr, surrogate_kinds()))}")
    return _REGISTERED.pop(kind)


def surrogate_kinds() -> tuple[str, ...]:
    """The kinds a surrogate file or ``--model`` may name: the built-ins, then the
    registered ones in the order of registration (imports nothing)."""
    return tuple(BUILTIN_SURROGATES) + tuple(k for k in _REGISTERED if k not in BUILTIN_SURROGATES)


def surrogate_class(kind: str, name: str = "model") -> type:
    """The model class of ``kind`` (``name``: what the message calls the value).

    Raises:
        ConfigError: no model of that kind is registered (the message lists the kinds).
    """
    cls = _REGISTERED.get(kind) if isinstance(kind, str) else None
    if cls is None and isinstance(kind, str) and kind in BUILTIN_SURROGATES:
        module, name = BUILTIN_SURROGATES[kind]
        cls = _REGISTERED[kind] = getattr(importlib.import_module(module), name)
    if cls is None:
        raise ConfigError(f"{name} must be one of {', '.join(map(repr, surrogate_kinds()))}, got {kind!r} "
                          "(the registered surrogate models; register another with "
                          "jaxsync.surrogate.register_surrogate before naming it)")
    return cls
