"""A sweep file (``mbavo sweep SWEEP.yaml``): which sequences, which configurations, which peers;
read, checked up front (one-line errors) and expanded into runs. JAX-free.

A list value makes a product: ``seed: [1, 2, 3]`` in a generated sequence gives three sequences,
``tracker.n: [1, 64]`` in a configuration gives two configurations (a setting that is itself a
list, e.g. ``tracker.points``, takes a list of lists for a product).
"""

from __future__ import annotations

import dataclasses
import itertools
import pathlib
import re
import typing

from ..config import PRESETS, SECTIONS, BenchConfig, SynthConfig, _yaml_value, load_config, refuse_command_line_only
from ..errors import ConfigError
from ..methods import ODOMETRY_METHODS
from ..names import check_name

__all__ = ["PEERS", "SequenceSpec", "SweepSpec", "Task", "load_sweep", "parse_sweep", "as_overrides", "expand", "check_names"]

PEERS = tuple(m for m in ODOMETRY_METHODS if not m.startswith("ours_"))
TOP_KEYS = ("sequences", "configurations", "peers", "base", "config", "peer_depth_max")
SYNTH_KEYS = tuple(f.name for f in dataclasses.fields(SynthConfig))


@dataclasses.dataclass(frozen=True)
class SequenceSpec:
    """One sequence of a sweep: an existing folder (``path``), a generated one (``synth``: the
    SynthConfig values) or a real RGB-D clip blurred along known paths (``source``, ``blur_px``,
    ``seed``); generated ones go to ``<out>/data/<name>``."""

    name: str
    path: str = ""
    synth: dict = dataclasses.field(default_factory=dict)
    source: str = ""
    blur_px: float = 20.0
    seed: int = 0

    @property
    def generated(self) -> bool:
        return not self.path


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """Sequences x methods: ``configurations`` (name -> ``section.key=value`` overrides, ``base``
    included) and ``peers`` (open3d, open3d_color, opencv); ``config``: a YAML under every run."""

    sequences: tuple[SequenceSpec, ...]
    configurations: dict[str, tuple[str, ...]]
    peers: tuple[str, ...] = ()
    base: tuple[str, ...] = ()
    config: str = ""
    peer_depth_max: float = BenchConfig().peer_depth_max

    @property
    def methods(self) -> list[str]:
        return [*self.configurations, *self.peers]


@dataclasses.dataclass(frozen=True)
class Task:
    """One run: ``method`` over the sequence folder ``data``, outputs in ``out``; ours with
    ``overrides`` (on ``config``), or the peer ``peer``."""

    sequence: str
    method: str
    data: str
    out: str
    overrides: tuple[str, ...] = ()
    config: str = ""
    peer: str = ""
    peer_depth_max: float = BenchConfig().peer_depth_max
    code: str = ""  # the version of mbavo_jax's code that runs it (runner.code_version)

    def identity(self) -> dict:
        """What makes a finished run reusable: everything about the task (JSON-ready)."""
        return {**dataclasses.asdict(self), "overrides": list(self.overrides)}


# ------------------------------------------------------------------------------------- products


def _value_text(v) -> str:
    text = "-".join(_value_text(x) for x in v) if isinstance(v, (list, tuple)) else _yaml_value(v)
    return re.sub(r"[^A-Za-z0-9_.+-]", "", text)


def expand(name: str, values: dict, is_product) -> list[tuple[str, dict]]:
    """Every combination of the values for which ``is_product(key, value)``: (name with
    ``_<key>=<value>`` per such key (last part of a dotted key), one value per key)."""
    listed = [k for k, v in values.items() if is_product(k, v)]
    out = []
    for combo in itertools.product(*(values[k] for k in listed)):
        chosen = dict(zip(listed, combo))
        label = "_".join([name, *(f"{k.split('.')[-1]}={_value_text(v)}" for k, v in chosen.items())])
        out.append((label, {**values, **chosen}))
    return out


def _no_empty_product(where: str, what: str, values: dict, is_product) -> None:
    """A key whose list is empty would make an empty product (nothing to run): one line instead."""
    empty = [str(k) for k, v in values.items() if is_product(k, v) and not v]
    if empty:
        raise ConfigError(f"{where}: {what}: {empty[0]}: [] is an empty list, which gives no runs (give at least one value)")


def _setting_is_list(key: str) -> bool:
    section, _, field = key.partition(".")
    cls = SECTIONS.get(section)
    hint = typing.get_type_hints(cls).get(field) if cls else None
    return typing.get_origin(hint) is tuple


def _override_product(key: str, value) -> bool:
    """A list of values, unless the setting is a list itself (then a list of lists)."""
    if not isinstance(value, list):
        return False
    return not _setting_is_list(key) or all(isinstance(v, list) for v in value)


def as_overrides(values: dict, section: str = "") -> tuple[str, ...]:
    """``{"tracker.n": 32}`` (or ``{"n": 32}`` with ``section="tracker"``) as ``("tracker.n=32",)``."""
    prefix = f"{section}." if section else ""
    return tuple(f"{prefix}{k}={_yaml_value(tuple(v) if isinstance(v, list) else v)}" for k, v in values.items())


# ---------------------------------------------------------------------------------------- parsing


def _mapping(where: str, value, what: str) -> dict:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: {what} must be a mapping, got {type(value).__name__}")
    return value


def _unknown(where: str, keys, allowed, what: str) -> None:
    bad = [str(k) for k in keys if k not in allowed]
    if bad:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(bad)} in {what} (allowed: {', '.join(allowed)})")


def _sequence_entries(where: str, i: int, entry) -> list[SequenceSpec]:
    """One entry of ``sequences:``: ``path:``, ``preset:`` (with SynthConfig keys) or ``from:``."""
    what = f"sequences[{i}]"
    if isinstance(entry, str):
        entry = {"path": entry}
    entry = dict(_mapping(where, entry, what))
    kinds = [k for k in ("path", "preset", "from") if k in entry]
    if len(kinds) != 1:
        raise ConfigError(f"{where}: {what} needs exactly one of path:, preset: or from:, got {', '.join(kinds) or 'none'}")
    kind, name = kinds[0], entry.pop("name", None)
    if kind == "path":
        _unknown(where, entry, ("path",), what)
        return [SequenceSpec(str(name or pathlib.Path(str(entry["path"])).name), path=str(entry["path"]))]
    is_list = lambda k, v: isinstance(v, list)
    _no_empty_product(where, what, entry, is_list)
    if kind == "from":
        _unknown(where, entry, ("from", "blur_px", "seed"), what)
        base = str(name or f"{pathlib.Path(str(entry['from'])).name}_blurred")
        try:
            return [SequenceSpec(label, source=str(v["from"]), blur_px=float(v.get("blur_px", 20.0)), seed=int(v.get("seed", 0)))
                    for label, v in expand(base, entry, is_list)]
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: {what}: blur_px and seed must be numbers ({exc})") from None
    _unknown(where, entry, ("preset", *SYNTH_KEYS), what)
    out = []
    for label, v in expand(str(name or entry["preset"]), entry, is_list):
        preset = v.pop("preset")
        if preset not in PRESETS:
            raise ConfigError(f"{where}: {what}: unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
        synth = {**PRESETS[preset], **v}
        try:
            SynthConfig(**synth)
        except (ConfigError, TypeError) as exc:
            raise ConfigError(f"{where}: {what}: {exc}") from None
        out.append(SequenceSpec(label, synth=synth))
    return out


def _configurations(where: str, raw, base: tuple[str, ...], config: str) -> dict[str, tuple[str, ...]]:
    """Named overrides, expanded over their lists and each checked with ``load_config``."""
    out = {}
    for name, values in _mapping(where, raw, "configurations").items():
        values = _mapping(where, values, f"configurations.{name}")
        _no_empty_product(where, f"configurations.{name}", values, _override_product)
        for label, chosen in expand(str(name), values, _override_product):
            overrides = (*base, *as_overrides(chosen))
            try:
                load_config(config or None, list(overrides))
            except ConfigError as exc:
                raise ConfigError(f"{where}: configurations.{name}: {exc}") from None
            out[label] = overrides
    return out


def check_names(where: str, spec: SweepSpec) -> None:
    """Every sequence and method name is a safe folder name (``names.check_name``), none twice."""
    for what, names in (("sequence", [s.name for s in spec.sequences]), ("method", spec.methods)):
        for n in names:
            check_name(n, where, what)
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ConfigError(f"{where}: {what} name(s) {', '.join(twice)} appear twice (give each a name:)")


def parse_sweep(data, where: str = "sweep") -> SweepSpec:
    """The sweep described by ``data`` (the YAML's content); ConfigError (one line) on any problem."""
    data = _mapping(where, data, "the sweep file")
    _unknown(where, data, TOP_KEYS, "the sweep file")
    seqs = data.get("sequences")
    if not isinstance(seqs, list) or not seqs:
        raise ConfigError(f"{where}: sequences: must be a non-empty list (path: DIR, or preset: strong with seed:, frames:, ...)")
    config = str(data.get("config") or "")
    base = as_overrides(_mapping(where, data.get("base"), "base"))
    peers = data.get("peers") or []
    if not isinstance(peers, list) or any(p not in PEERS for p in peers):
        raise ConfigError(f"{where}: peers: must be a list of {', '.join(PEERS)}, got {peers!r}")
    try:
        load_config(config or None, list(base))
        depth_max = BenchConfig(peer_depth_max=data.get("peer_depth_max", BenchConfig().peer_depth_max)).peer_depth_max
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    spec = SweepSpec(sequences=tuple(s for i, e in enumerate(seqs) for s in _sequence_entries(where, i, e)),
                     configurations=_configurations(where, data.get("configurations"), base, config),
                     peers=tuple(peers), base=base, config=config, peer_depth_max=depth_max)
    if not spec.methods:
        raise ConfigError(f"{where}: nothing to run: give configurations: (e.g. ours: {{}}) or peers:")
    check_names(where, spec)
    refuse_command_line_only(where, data)
    return spec


def load_sweep(path) -> SweepSpec:
    """The sweep file at ``path``, read and checked (see :func:`parse_sweep`)."""
    import yaml

    from ..io import read_text

    p = pathlib.Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: sweep file not found")
    try:
        data = yaml.safe_load(read_text(p, "sweep file"))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({str(exc).splitlines()[0]})") from None
    return parse_sweep(data, str(p))
