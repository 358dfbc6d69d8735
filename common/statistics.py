"""Per-trajectory statistics: a per-step signal and an aggregation over any range of steps.

Torch-free and dataset-free: the remote runner measures a live episode with the same definitions that
relabelling (`gmt.model.data.statistics`) and evaluation apply to datasets.

A statistic is named by any of (`get_statistic`):
- an expression `AGG(SOURCE)`: AGG one of mean, sum, min, max, first, last, std; SOURCE `reward`, `info.KEY`,
  `obs[i]` (the observation the action was taken at, flattened) or `action[i]` (a Discrete action is
  `action[0]`), optionally inside `abs(...)`; e.g. `mean(info.x_velocity)`, `sum(reward)`, `mean(abs(obs[2]))`.
  Parsed by a regular expression, never evaluated.
- a registered name: `mean_x_velocity` (= `mean(info.x_velocity)`), `return` (= `sum(reward)`), `mean_reward`
  (= `mean(reward)`), or one a package registers in the `gmt.statistics` entry-point group.
- a plug-in `module:function` (or `AGG(module:function)`): `function(reward, info, obs, action) -> float` is the
  per-step signal, aggregated by mean unless AGG says otherwise; an optional `requires` attribute (a set of info
  keys) names the infos it reads. A module attribute that is a `Statistic` is used as it is.

Evaluation needs the value over step ranges (e.g. steps [100, 1000)), so every statistic is defined by
`per_step(episode) -> [T]` and `aggregate(values) -> float`; `of_episode` is the aggregate over all steps.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from gmt.common.plugins import load_attribute

Signal = Callable[[float, Mapping[str, float]], float]
Aggregation = Callable[[np.ndarray], float]
ENTRY_POINT_GROUP = "gmt.statistics"


class Episode(Protocol):
    """What a statistic reads of an episode (e.g. `gmt.model.data.minari_io.Episode`)."""

    rewards: np.ndarray
    infos: Mapping[str, np.ndarray]
    observations: np.ndarray
    actions: np.ndarray

    def __len__(self) -> int: ...


class MissingInfoError(KeyError):
    """A statistic needs info keys (or observation/action entries) the data does not have."""

    def __str__(self) -> str:  # KeyError would print the message quoted
        return str(self.args[0])


class StatisticError(KeyError):
    """A statistic name that is neither an expression, a registered name nor an importable plug-in."""

    def __str__(self) -> str:
        return str(self.args[0])


def _sum(values: np.ndarray) -> float:
    return float(np.sum(values))


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values))


def _first(values: np.ndarray) -> float:
    return float(values[0]) if len(values) else float("nan")


def _last(values: np.ndarray) -> float:
    return float(values[-1]) if len(values) else float("nan")


def _min(values: np.ndarray) -> float:
    return float(np.min(values)) if len(values) else float("nan")


def _max(values: np.ndarray) -> float:
    return float(np.max(values)) if len(values) else float("nan")


def _std(values: np.ndarray) -> float:
    return float(np.std(values))


AGGREGATIONS: dict[str, Aggregation] = {
    "mean": _mean,
    "sum": _sum,
    "min": _min,
    "max": _max,
    "first": _first,
    "last": _last,
    "std": _std,
}


@dataclass(frozen=True)
class Statistic:
    """A per-trajectory statistic.

    Attributes:
        name: The name it was asked for, e.g. "mean_x_velocity" or "mean(abs(obs[2]))".
        signal: Per-step value from the step's reward and info.
        aggregate: Reduces per-step values to one number (mean, sum, ...).
        requires: Info keys the signal reads.
        description: One line for listings.
    """

    name: str
    signal: Signal
    aggregate: Aggregation
    requires: frozenset[str] = field(default_factory=frozenset)
    description: str = ""

    def step(self, reward: float, info: Mapping[str, Any], obs: Any = None, action: Any = None) -> float:
        """The signal of one step: its reward and info, the observation the action was taken at, the action."""
        return float(self.signal(float(reward), info))

    def per_step(self, episode: Episode) -> np.ndarray:
        """The signal at every step of `episode`, shape [T]."""
        missing = self.requires - set(episode.infos)
        if missing:
            raise MissingInfoError(missing_message(self, set(episode.infos)))
        n = len(episode)
        obs, act = getattr(episode, "observations", None), getattr(episode, "actions", None)
        return np.asarray(
            [
                self.step(
                    float(episode.rewards[t]),
                    {k: episode.infos[k][t] for k in episode.infos},
                    None if obs is None else obs[t],
                    None if act is None else act[t],
                )
                for t in range(n)
            ],
            dtype=np.float64,
        )

    def of_episode(self, episode: Episode) -> float:
        """The statistic of a whole episode."""
        return float(self.aggregate(self.per_step(episode)))


@dataclass(frozen=True)
class FieldStatistic(Statistic):
    """An expression `AGG(SOURCE)`: the signal is one source per step, optionally its absolute value.

    Attributes:
        source: "reward", "info", "obs" or "action".
        key: The info key (source "info"), or the flat index (as a string) into the observation or action.
        absolute: Whether the signal is the source's absolute value.
        expression: The canonical expression, e.g. "mean(abs(obs[2]))".
    """

    source: str = "reward"
    key: str | None = None
    absolute: bool = False
    expression: str = ""

    def _finish(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        return np.abs(x) if self.absolute else x

    def _entry(self, value: Any, what: str) -> float:
        if value is None:
            raise MissingInfoError(f"statistic {self.name!r} reads {what}[{self.key}], which was not given")
        flat = np.asarray(value).reshape(-1)
        i = int(self.key or 0)
        if i >= flat.size:
            raise MissingInfoError(
                f"statistic {self.name!r} reads {what}[{i}], but the {what} has {flat.size} entries"
            )
        return float(flat[i])

    def step(self, reward: float, info: Mapping[str, Any], obs: Any = None, action: Any = None) -> float:
        if self.source == "reward":
            v = float(reward)
        elif self.source == "info":
            if self.key not in info:
                raise MissingInfoError(missing_message(self, set(info)))
            v = float(info[self.key])
        else:
            v = self._entry(obs if self.source == "obs" else action, self.source)
        return abs(v) if self.absolute else v

    def per_step(self, episode: Episode) -> np.ndarray:
        if self.source == "reward":
            return self._finish(episode.rewards)
        if self.source == "info":
            if self.key not in episode.infos:
                raise MissingInfoError(missing_message(self, set(episode.infos)))
            return self._finish(episode.infos[self.key])
        arr = np.asarray(episode.observations if self.source == "obs" else episode.actions)
        flat = arr.reshape(len(arr), -1) if len(arr) else arr.reshape(0, 1)
        i = int(self.key or 0)
        if i >= flat.shape[1]:
            raise MissingInfoError(
                f"statistic {self.name!r} reads {self.source}[{i}], but the data's {self.source} has "
                f"{flat.shape[1]} entries per step"
            )
        return self._finish(flat[:, i])


_SOURCE = r"reward|info\.[A-Za-z_][\w.\-]*|(?:obs|action)\[\d+\]"
_PLUGIN = r"(?P<module>[A-Za-z_][\w.]*):(?P<func>[A-Za-z_]\w*)"
_EXPR = re.compile(
    rf"(?P<agg>{'|'.join(AGGREGATIONS)})\(\s*(?:abs\(\s*(?P<abs_src>{_SOURCE})\s*\)|(?P<src>{_SOURCE})|"
    rf"(?P<plugin>{_PLUGIN}))\s*\)"
)
_BARE_PLUGIN = re.compile(_PLUGIN)
# The names statistics had before expressions; they stay registered under these names.
ALIASES = {"mean_x_velocity": "mean(info.x_velocity)", "return": "sum(reward)", "mean_reward": "mean(reward)"}

_REGISTRY: dict[str, Statistic] = {}


def _compact(text: str) -> str:
    """`text` without spaces, or "" where a space splits a word (e.g. "true x"), which nothing matches."""
    return "" if re.search(r"\w\s+\w", text) else re.sub(r"\s+", "", text)


def parse_expression(text: str, name: str | None = None) -> FieldStatistic | None:
    """The statistic of an `AGG(SOURCE)` expression, or None when `text` is not one (plug-ins excluded)."""
    m = _EXPR.fullmatch(_compact(text))
    if m is None or m["plugin"]:
        return None
    agg, absolute = m["agg"], m["abs_src"] is not None
    src = m["abs_src"] or m["src"]
    if src == "reward":
        source, key = "reward", None
    elif src.startswith("info."):
        source, key = "info", src[len("info.") :]
    else:
        source, key = ("obs" if src.startswith("obs") else "action"), str(int(re.search(r"\d+", src)[0]))
    inner = src if source in ("reward", "info") else f"{source}[{key}]"
    expr = f"{agg}(abs({inner}))" if absolute else f"{agg}({inner})"
    what = {"reward": "the reward", "info": f"info {key!r}", "obs": f"observation entry {key}"}.get(
        source, f"action entry {key}"
    )
    return FieldStatistic(
        name or expr,
        lambda reward, info: float("nan"),  # unused: FieldStatistic.step reads the source itself
        AGGREGATIONS[agg],
        frozenset({key}) if source == "info" else frozenset(),
        f"{agg} of {'|' if absolute else ''}{what}{'|' if absolute else ''} per step",
        source=source,
        key=key,
        absolute=absolute,
        expression=expr,
    )


class _PluginStatistic(Statistic):
    """A `module:function` plug-in: `function(reward, info, obs, action) -> float` per step."""

    def step(self, reward: float, info: Mapping[str, Any], obs: Any = None, action: Any = None) -> float:
        missing = self.requires - set(info)
        if missing:
            raise MissingInfoError(missing_message(self, set(info)))
        return float(self.signal(float(reward), info, obs, action))  # type: ignore[call-arg]


def _from_object(name: str, obj: Any, agg: str = "mean") -> Statistic:
    if isinstance(obj, Statistic):
        return obj
    if not callable(obj):
        raise StatisticError(f"statistic {name!r}: {obj!r} is neither a Statistic nor a per-step function")
    requires = frozenset(getattr(obj, "requires", ()) or ())
    doc = (obj.__doc__ or "").strip().splitlines()
    return _PluginStatistic(name, obj, AGGREGATIONS[agg], requires, doc[0] if doc else f"plug-in {name}")


def _plugin(name: str, module: str, func: str, agg: str) -> Statistic:
    try:
        obj = load_attribute(module, func)
    except (ImportError, AttributeError) as e:
        raise StatisticError(f"statistic {name!r}: cannot import {module}:{func} ({e})") from None
    return _from_object(name, obj, agg)


def _entry_point(name: str) -> Statistic | None:
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name == name:
            return _from_object(name, ep.load())
    return None


def register(stat: Statistic, overwrite: bool = False) -> Statistic:
    """Add a statistic to the registry under `stat.name`."""
    if stat.name in _REGISTRY and not overwrite:
        raise ValueError(f"statistic {stat.name!r} is already registered")
    _REGISTRY[stat.name] = stat
    return stat


def register_statistic(
    name: str, aggregate: Aggregation = np.mean, requires: set[str] | None = None, description: str = ""
) -> Callable[[Signal], Signal]:
    """Decorator: register `fn(reward, info) -> float` as the per-step signal of statistic `name`."""

    def deco(fn: Signal) -> Signal:
        register(Statistic(name, fn, aggregate, frozenset(requires or ()), description or (fn.__doc__ or "")))
        return fn

    return deco


def statistic_names(name: str) -> list[str]:
    """The statistics of a comma-separated list ("mean(info.x_velocity), mean(abs(action[0]))"): goals over
    several statistics at once (`gmt.model.data.relabel`). One name gives a list of one."""
    return [part.strip() for part in name.split(",")]


def get_statistic(name: str, plugins: bool = True) -> Statistic:
    """The statistic `name`: an expression, a registered or entry-point name, or a `module:function` plug-in.

    A comma-separated list names goals over several statistics; each is checked, and the first is returned: the
    one a model's goals are ordered, evaluated and measured by (their table keeps every goal's vector).

    Args:
        name: What the user wrote (module docstring).
        plugins: Whether a `module:function` may be imported (False for names that came from a server).

    Raises:
        StatisticError: If `name` is none of these, saying what is accepted.
    """
    if name in _REGISTRY:
        return _REGISTRY[name]
    if "," in name:
        first, *rest = statistic_names(name)
        for other in rest:
            get_statistic(other, plugins)
        return get_statistic(first, plugins)
    stat = parse_expression(name)
    if stat is not None:
        return stat
    compact = _compact(name)
    m = _EXPR.fullmatch(compact)
    bare = _BARE_PLUGIN.fullmatch(compact)
    if m is not None or bare is not None:
        if not plugins:
            raise StatisticError(
                f"statistic {name!r} is a plug-in; pass it yourself (--statistic {name}) to import it here"
            )
        g = m or bare
        return _plugin(name, g["module"], g["func"], m["agg"] if m is not None else "mean")
    found = _entry_point(name)
    if found is not None:
        return found
    raise StatisticError(
        f"unknown statistic {name!r}: write AGG(SOURCE) with AGG one of {', '.join(AGGREGATIONS)} and SOURCE "
        "reward, info.KEY, obs[i] or action[i] (optionally abs(...)), e.g. mean(info.x_velocity), or "
        f"module:function; registered names: {', '.join(sorted(_REGISTRY))}"
    )


def canonical(name: str) -> str:
    """The expression a registered alias stands for (`return` -> `sum(reward)`), else `name` itself."""
    if name in ALIASES:
        return ALIASES[name]
    if "," in name:
        return ", ".join(canonical(n) for n in statistic_names(name))
    stat = parse_expression(name)
    return stat.expression if stat is not None else name


def list_statistics() -> list[str]:
    """Names of all registered statistics."""
    return sorted(_REGISTRY)


def available_statistics(info_keys: set[str]) -> list[str]:
    """Registered statistics computable from data having `info_keys`."""
    return sorted(n for n, s in _REGISTRY.items() if s.requires <= info_keys)


def default_statistic(info_keys: set[str]) -> tuple[str, str]:
    """The statistic to cluster when none is given, and why: mean x-velocity where the data records it, else the
    return (every dataset has rewards)."""
    if "x_velocity" in info_keys:
        return "mean_x_velocity", "the data's infos record x_velocity"
    return "return", "the data's infos have no x_velocity"


def missing_message(stat: Statistic, info_keys: set[str]) -> str:
    """Error text: what is missing and which statistics remain available."""
    missing = sorted(stat.requires - info_keys)
    return (
        f"statistic {stat.name!r} needs per-step info {missing}, which this data does not record "
        f"(its infos: {sorted(info_keys) or 'none'}); statistics still available: "
        f"{', '.join(available_statistics(info_keys)) or 'none'}, or any AGG(reward|obs[i]|action[i])"
    )


def signal_from_step(
    name: str,
    reward: float,
    info: Mapping[str, Any],
    obs: Any = None,
    action: Any = None,
    plugins: bool = True,
) -> float:
    """The per-step signal of statistic `name` for one live `env.step`: its reward and info, the observation the
    action was taken at and the action.

    Raises:
        MissingInfoError: If the step lacks what the statistic reads.
    """
    stat = get_statistic(name, plugins=plugins)
    if not stat.requires <= set(info):
        raise MissingInfoError(missing_message(stat, set(info)))
    return stat.step(reward, info, obs, action)


def aggregate(name: str, values: np.ndarray | list[float]) -> float:
    """Aggregate per-step signals of statistic `name` (e.g. over a step range) into its value."""
    return float(get_statistic(name).aggregate(np.asarray(values, dtype=np.float64)))


def is_sum(name: str) -> bool:
    """Whether statistic `name` sums its per-step signal (e.g. `return`): a segment's value is then a sum over
    that segment, not comparable with a whole episode's value. Names that do not resolve are not sums."""
    try:
        return get_statistic(name, plugins=False).aggregate is _sum
    except KeyError:
        return False


for _alias, _expr in ALIASES.items():
    register(parse_expression(_expr, name=_alias))
