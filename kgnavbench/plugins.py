"""Stage 6 — plugins: the baseline plugin interface and its registry.

A plugin is one Python file in `baselines/` (the file name is the method name, `--method NAME`), or
a module registered under the `kgnavbench.baselines` entry-point group by another package. It defines

    DESCRIPTION = "one line: what the method is"          # required
    PRIVILEGED = False                                    # optional; True: may read infos["expert_action"]

    @dataclass
    class Config:                                         # optional; its fields are the method's options
        stop_probability: float = 0.1                     #   (`--set stop_probability=0.2`)

    def make_policy(config: Config, spec: PolicySpec) -> Policy   # required

and the policy it returns has two methods:

    reset(agent: str) -> None                             # a new episode begins for this agent
    act(observations: dict[str, dict], infos: dict[str, dict]) -> dict[str, int]
                                                          # one action (0..9) per agent in observations

`observations` and `infos` are exactly what `kgnavbench.env` returns for the live agents (infos
without "expert_action" unless PRIVILEGED). The README has a worked example; `baselines/random_walk.py`
is the one to copy.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import sys
import typing
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from types import ModuleType

from .kitchens import object_types
from .tasks import VIEW_SIZE
from .world import ACTIONS

BASELINES_DIR = Path(__file__).resolve().parent.parent / "baselines"
ENTRY_POINT_GROUP = "kgnavbench.baselines"


class PluginError(ValueError):
    """A plugin that is missing, fails to import or breaks the interface; or a bad option."""


@dataclass(frozen=True)
class PolicySpec:
    """What a policy may know about the environment before it starts."""

    n_actions: int = len(ACTIONS)
    actions: tuple[str, ...] = ACTIONS
    view_size: int = VIEW_SIZE
    object_types: tuple[str, ...] = ()
    seed: int = 0

    @staticmethod
    def default(seed: int = 0, view_size: int = VIEW_SIZE) -> PolicySpec:
        return PolicySpec(view_size=view_size, object_types=object_types(), seed=seed)


@dataclass(frozen=True)
class Plugin:
    name: str
    source: str  # file path or entry point, for error messages
    description: str
    privileged: bool
    config_class: type
    module: ModuleType

    def config(self, options: dict[str, str] | None = None):
        """The typed config with `options` (strings, as typed on the command line) applied."""
        return make_config(self, options or {})

    def make_policy(self, config, spec: PolicySpec):
        try:
            policy = self.module.make_policy(config, spec)
        except Exception as e:
            raise PluginError(f"{self.source}: make_policy failed: {type(e).__name__}: {e}") from e
        missing = [m for m in ("reset", "act") if not callable(getattr(policy, m, None))]
        if missing:
            raise PluginError(
                f"{self.source}: the policy from make_policy has no {' or '.join(m + '()' for m in missing)} "
                "(see kgnavbench/plugins.py for the interface)"
            )
        return policy


@dataclass
class _NoOptions:
    """A plugin without a Config class takes no options."""


def plugin_sources() -> dict[str, str]:
    """Method name -> where its plugin comes from (a baselines/ file or an entry point)."""
    found = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        found[ep.name] = f"entry point {ep.name} = {ep.value}"
    if BASELINES_DIR.is_dir():
        for path in sorted(BASELINES_DIR.glob("*.py")):
            if not path.name.startswith("_"):
                found[path.stem] = str(path)
    return dict(sorted(found.items()))


def available() -> list[str]:
    return list(plugin_sources())


def load_plugin(name: str) -> Plugin:
    """Import and check the plugin NAME; every problem is a PluginError naming the file."""
    sources = plugin_sources()
    if name not in sources:
        raise PluginError(f"unknown method {name!r}; available: {', '.join(sources) or 'none'}")
    source = sources[name]
    try:
        if source.startswith("entry point"):
            (ep,) = [e for e in entry_points(group=ENTRY_POINT_GROUP) if e.name == name]
            module = ep.load()
        else:
            spec = importlib.util.spec_from_file_location(f"kgnavbench_baselines.{name}", source)
            module = importlib.util.module_from_spec(spec)
            sys.modules[spec.name] = module  # dataclasses look their module up here
            spec.loader.exec_module(module)
    except Exception as e:
        raise PluginError(f"{source}: failed to import: {type(e).__name__}: {e}") from e
    return check_plugin(name, source, module)


def check_plugin(name: str, source: str, module: ModuleType) -> Plugin:
    problems = []
    description = getattr(module, "DESCRIPTION", None)
    if not isinstance(description, str) or not description.strip():
        problems.append('DESCRIPTION = "one line" is missing')
    if not callable(getattr(module, "make_policy", None)):
        problems.append("make_policy(config, spec) is missing")
    config_class = getattr(module, "Config", _NoOptions)
    if not dataclasses.is_dataclass(config_class):
        problems.append("Config must be a @dataclass")
    privileged = getattr(module, "PRIVILEGED", False)
    if not isinstance(privileged, bool):
        problems.append("PRIVILEGED must be True or False")
    if problems:
        raise PluginError(f"{source} is not a kgnavbench plugin: " + "; ".join(problems))
    return Plugin(name, source, description.strip(), privileged, config_class, module)


def make_config(plugin: Plugin, options: dict[str, str]):
    fields = {f.name: f for f in dataclasses.fields(plugin.config_class)}
    hints = typing.get_type_hints(plugin.config_class)
    values = {}
    for key, text in options.items():
        if key not in fields:
            known = ", ".join(fields) or "none"
            raise PluginError(f"{plugin.source}: unknown option {key!r} for {plugin.name} (options: {known})")
        values[key] = _convert(plugin, key, hints.get(key, str), text)
    return plugin.config_class(**values)


def _convert(plugin: Plugin, key: str, kind, text):
    if not isinstance(text, str):
        return text
    try:
        if kind is bool:
            if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError("not a boolean")
            return text.lower() in ("true", "1", "yes")
        if kind in (int, float, str):
            return kind(text)
        return text
    except ValueError as e:
        kind_name = getattr(kind, "__name__", kind)
        raise PluginError(f"{plugin.source}: option {key}={text!r} is not a {kind_name}") from e


def parse_options(items: list[str]) -> dict[str, str]:
    """['a=1', 'b=x'] -> {'a': '1', 'b': 'x'}."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise PluginError(f"option {item!r} is not KEY=VALUE")
        out[key.strip()] = value.strip()
    return out
