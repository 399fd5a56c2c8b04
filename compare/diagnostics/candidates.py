"""The candidate effects: the registry, factories (a name, an Effect class or instance, a
plugin file's effects), and what an effect says of itself (applicable, left out by default,
constant, plausible, understated by its score test)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from flexforce.errors import ConfigError
from flexforce.factors.effects.base import traits


def registered_effects() -> dict:
    """The built-in effect catalogue (``flexforce.factors.effects.EFFECTS``), empty until it exists."""
    try:
        from flexforce.factors.effects import EFFECTS
    except ImportError:
        return {}
    return dict(EFFECTS)


def _is_effect(obj) -> bool:
    from flexforce.factors.effects import Effect

    return isinstance(obj, Effect)


def effect_factory(spec) -> tuple[str, Callable[[], object]]:
    """``(name, make)`` for a candidate: a registered name, an Effect instance or an Effect class.

    A fresh instance is made for every fit when the candidate is a class or a name; an instance
    is shared (effects are descriptions, their values live in the smoother's state).
    """
    if isinstance(spec, str):
        reg = registered_effects()
        if spec not in reg:
            known = ", ".join(sorted(reg)) or "none registered (flexforce.factors.effects is not available)"
            raise ConfigError(f"unknown effect '{spec}'; known: {known}")
        try:
            from flexforce.factors.effects import make_effect
        except ImportError:  # a registry without the factory
            make_effect = None  # type: ignore[assignment]
        make = (lambda: make_effect(spec)) if make_effect else reg[spec]  # type: ignore[truthy-function]
        eff = make()
        return eff.name, make
    if isinstance(spec, type):
        eff = spec()
        if not _is_effect(eff):
            raise ConfigError(f"{spec.__name__} does not implement the Effect protocol (name, dim, labels, prior, "
                              "random_walk_sigma, residual_terms, report)")
        return eff.name, spec
    if _is_effect(spec):
        return spec.name, lambda: spec
    raise ConfigError(f"candidate {spec!r} is neither an effect name, an Effect class nor an Effect instance")


def bound(make: Callable[[], object], rec, model) -> Callable[[], object]:
    """``make`` whose effects are fitted to ``rec``: an effect with a ``bind(rec, model)`` method
    (one unknown block per contact of the recording, e.g. the footholds) is made through it."""
    def made():
        eff = make()
        bind = traits(eff).bind
        return bind(rec, model) if callable(bind) else eff

    return made


def resolve_candidates(candidates: Iterable | None) -> dict[str, Callable[[], object]]:
    """Name -> factory of every candidate (default: every registered effect)."""
    if candidates is None:
        candidates = list(registered_effects())
        if not candidates:
            raise ConfigError("no candidate effects: flexforce.factors.effects is not available; pass candidates")
    out: dict[str, Callable[[], object]] = {}
    for spec in candidates:
        name, make = effect_factory(spec)
        if name in out:
            raise ConfigError(f"two candidate effects are named '{name}'; effect names must be unique")
        out[name] = make
    return out


def _constant_effect(make: Callable[[], object], prob) -> bool:
    """Whether the effect ``make()`` is one global block (a constant) in ``prob``'s smoother; False
    for a per-step effect or one that cannot be made (its test reports that)."""
    from flexforce.smoother.linearize import is_global

    try:
        return bool(is_global(make(), prob))
    except Exception:  # a user's effect may raise anything: its own test says what
        return False


def _score_understates(make: Callable[[], object]) -> bool:
    """Whether the effect ``make`` builds says its score test understates it (``score_understates``)."""
    try:
        return bool(traits(make()).score_understates)
    except Exception:  # noqa: BLE001 - a plugin that cannot be built fails where it is fitted, with its reason
        return False


def _constant(effect, prob) -> bool:
    """Whether the smoothers fit ``effect``'s unknowns as one global block
    (:func:`flexforce.smoother.linearize.is_global`); False when a user's effect cannot say."""
    from flexforce.smoother.linearize import is_global

    try:
        return is_global(effect, prob)
    except Exception:  # a user's effect may raise anything: not taken for a constant
        return False


def inapplicable(rec, model, makers: dict[str, Callable[[], object]]) -> dict[str, str]:
    """Name -> ``"<name>: <reason>"`` for the candidates whose optional ``applicable(problem)`` says
    they have nothing to act on in ``model`` (an F/T offset when the F/T readings are not fused):
    skipped with that line, never fitted.  A check that raises leaves its candidate to the tests."""
    checks: dict[str, Any] = {}
    for name, make in makers.items():
        try:
            eff = make()
        except Exception:  # the fit says what is wrong with it
            continue
        if callable(traits(eff).applicable):
            checks[name] = eff
    if not checks:
        return {}
    from flexforce.smoother import NoiseRule, Problem

    prob = Problem.build(rec, model, NoiseRule())
    out = {}
    for name, eff in checks.items():
        try:
            why = eff.applicable(prob)
        except Exception:
            continue
        if why:
            out[name] = f"{name}: {why}"
    return out


def left_out_by_default(rec, makers: dict[str, Callable[[], object]]) -> dict[str, str]:
    """Name -> ``"<name>: <reason>"`` for the candidates whose optional ``by_default(rec)`` says
    they are not worth their cost on this recording unless asked for (the footholds without a
    touch-down); they are tested when named in ``candidates``."""
    out = {}
    for name, make in makers.items():
        try:
            check = traits(make()).by_default
            why = check(rec) if callable(check) else None
        except Exception:  # the fit says what is wrong with it
            continue
        if why:
            out[name] = f"{name}: {why}"
    return out


def _plausibility(effect, report: dict, problem) -> str | None:
    """The effect's own ``plausible(report, problem)`` verdict (None without the method)."""
    check = traits(effect).plausible
    if check is None or not isinstance(report, dict):
        return None
    try:
        return check(report, problem)
    except Exception as err:  # a user's check that fails says so, it does not stop the diagnosis
        return f"its plausibility check raised {type(err).__name__}: {err}"


def load_plugin(path) -> list:
    """The user-written effects of a Python file: its ``EFFECTS`` (a dict or list of Effect classes
    or instances) if it defines one, else every class defined in it whose instances (made without
    arguments) implement the Effect protocol.

    Each is returned as a :class:`flexforce.factors.effects.base.CheckedEffect` instance naming
    ``path``: an effect whose prior, random walk or residual terms are not finite fails with the
    file and the effect named where it is screened or fitted.

    Raises:
        ConfigError: naming ``path``: it does not exist or is not a ``.py`` file; importing it
            raises (its error quoted); an ``EFFECTS`` entry that is not an Effect class or
            instance, or a class that cannot be made without arguments; no Effect found.
    """
    import importlib.util
    from pathlib import Path

    from flexforce.factors.effects.base import CheckedEffect

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"effect plugin {path} does not exist; expected a Python file defining Effect classes")
    if path.suffix != ".py":
        raise ConfigError(f"effect plugin {path} is not a Python file (suffix {path.suffix or 'none'!r}); expected a "
                          ".py file defining Effect classes")
    spec = importlib.util.spec_from_file_location(f"flexforce_plugin_{path.stem.replace('-', '_')}", path)
    if spec is None or spec.loader is None:
        raise ConfigError(f"effect plugin {path} cannot be imported; expected a .py file defining Effect classes")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except (Exception, SystemExit) as err:  # a user's file: any error is a configuration error
        raise ConfigError(f"cannot load effect plugin {path}: {type(err).__name__}: {err}") from err

    def made(obj, where: str):
        if isinstance(obj, type):
            try:
                inst = obj()
            except Exception as err:  # noqa: BLE001 - a user's constructor may raise anything
                raise ConfigError(f"effect plugin {path}: {where} {obj.__name__}() raised {type(err).__name__}: "
                                  f"{err}; expected an Effect class made without arguments") from err
        else:
            inst = obj
        if not _is_effect(inst):
            raise ConfigError(f"effect plugin {path}: {where} {obj!r} does not implement the Effect protocol (name, "
                              "dim, labels, prior, random_walk_sigma, residual_terms, report)")
        return CheckedEffect(inst, str(path))

    declared = getattr(module, "EFFECTS", None)
    if declared is not None:
        items = list(declared.values()) if isinstance(declared, dict) else list(declared)
        return _own_names([made(obj, "EFFECTS entry") for obj in items], path)
    found = []
    for obj in vars(module).values():
        if isinstance(obj, type) and obj.__module__ == module.__name__:
            try:
                inst = obj()
            except Exception:  # noqa: BLE001 - not an effect made without arguments: a helper class
                continue
            if _is_effect(inst):
                found.append(CheckedEffect(inst, str(path)))
    if not found:
        raise ConfigError(f"effect plugin {path} defines no Effect (name, dim, labels, prior, random_walk_sigma, "
                          "residual_terms, report)")
    return _own_names(found, path)


def _own_names(effects: list, path) -> list:
    """``effects``, unless one takes a built-in effect's name or two share one (a ConfigError: the
    plugin's would silently stand in for the built-in in a ranking)."""
    builtin = registered_effects()
    seen: set[str] = set()
    for eff in effects:
        if eff.name in builtin:
            raise ConfigError(f"effect plugin {path} defines effect '{eff.name}', the name of a built-in effect; "
                              "expected another name (the built-in's is ranked as it is)")
        if eff.name in seen:
            raise ConfigError(f"effect plugin {path} defines two effects named '{eff.name}'; expected one name each")
        seen.add(eff.name)
    return effects
