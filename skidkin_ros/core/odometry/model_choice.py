"""Which models a parameters source holds, and the rule for running or switching to one.

A model whose parameters the source does not hold would run its defaults (the ideal
differential drive) under a calibrated model's name. The node (at start-up and on a parameter
change), ``skidkin predict`` and :class:`~skidkin_ros.core.odometry.config.OdometryConfig` ask
these functions, so they refuse and warn in the same words. ``config`` re-exports them.
"""

from __future__ import annotations

from typing import Any, Iterable

from skidkin_ros.core.kinematics.augmented import AUGMENTED_NAME
from skidkin_ros.core.kinematics.models import MODELS
from skidkin_ros.errors import ParameterError

__all__ = ['models_given', 'augmented_given', 'models_held', 'missing_parameters',
           'default_parameters_warning', 'check_model_given', 'switches_model']


def models_given(names: Iterable[str]) -> tuple[str, ...]:
    """Return the models whose parameters ``names`` set (ideal_dd needs none), in order."""
    names = set(names)
    return tuple(m.name for m in MODELS.values()
                 if not m.params or any(f'models.{m.name}.{p.name}' in names for p in m.params))


def augmented_given(names: Iterable[str]) -> bool:
    """Tell whether ``names`` set an augmented model: its base (diagnose's file names it).

    Extensions alone do not: the base would be its default, ideal_dd, not a calibrated model.
    """
    return 'augmented.base' in set(names)


def models_held(names: Iterable[str]) -> tuple[str, ...]:
    """Return the models ``names`` set, ``augmented`` included when its base is."""
    names = set(names)
    return models_given(names) + ((AUGMENTED_NAME,) if augmented_given(names) else ())


def missing_parameters(model: str, given: Iterable[str], base: str | None = None) -> str | None:
    """Return the parameters ``model`` lacks in ``given`` to run a calibration (None: it has them).

    ``given`` holds model names (:func:`models_held`). ``augmented`` needs its base named
    (``augmented.base``) and, when ``base`` is passed, that base's parameters.
    """
    given = set(given)
    if model != AUGMENTED_NAME:
        return None if model in given else f'models.{model}.*'
    if AUGMENTED_NAME not in given:
        return 'augmented.base'
    return None if base is None or base in given else f'models.{base}.*'


def default_parameters_warning(model: str, given: Iterable[str],
                               base: str | None = None) -> str | None:
    """Return the warning for a model run with default parameters (None: it has its own).

    The node logs it at start-up and ``skidkin predict`` prints it, so the two say the same.
    """
    missing = missing_parameters(model, given, base)
    if missing is None:
        return None
    return (f'model {model!r} runs default parameters (an ideal drive): no {missing} parameter '
            'was given; load a calibrated file')


def check_model_given(model: str, given: Iterable[str], source: str,
                      base: str | None = None) -> None:
    """Refuse to switch to a model whose parameters ``source`` does not hold.

    Its defaults are the ideal differential drive: run under a calibrated model's name, they
    would look calibrated. ``augmented`` counts as given when its base was
    (:func:`augmented_given`): without it, it is ideal_dd with its extensions. Its base
    (``base``, when passed) must be given as any model is.
    """
    given = tuple(given)
    missing = missing_parameters(model, given, base)
    if missing is None:
        return
    others = ', '.join(m for m in given if m != AUGMENTED_NAME) or 'none'
    if missing == 'augmented.base':
        raise ParameterError(
            f'model {AUGMENTED_NAME!r} is not in {source}: no augmented.base was given, so it '
            'would run ideal_dd (its default base) with at most its extensions (an ideal '
            'drive), not a calibration; load the file `skidkin diagnose` writes, or choose '
            f'one of {others}')
    if model == AUGMENTED_NAME:
        raise ParameterError(
            f'model {AUGMENTED_NAME!r} runs the base model {base!r}, which is not in {source} '
            f'(it holds {others}): its parameters would be the defaults (an ideal drive), not a '
            'calibration; set augmented.base to one of those, or calibrate it')
    raise ParameterError(
        f'model {model!r} is not in {source} (it holds {", ".join(given) or "none"}): its '
        'parameters would be the defaults (an ideal drive), not a calibration; calibrate '
        'it, load a file that holds it, or choose one of those')


def switches_model(old: Any, new: Any) -> bool:
    """Tell whether ``new`` runs another model than ``old`` (for augmented: another base too).

    ``old``, ``new``: :class:`~skidkin_ros.core.odometry.config.OdometryConfig` (not imported:
    config imports this module).
    """
    return new.model != old.model or (new.model == AUGMENTED_NAME
                                      and new.augmented_base != old.augmented_base)
