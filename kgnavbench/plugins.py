"""Stage 10 — plugins: the baseline plugin interface and its registry.

A plugin is one Python file (the file name is the method name, `--method NAME`) in one of
  * the shipped baselines: the repository's `baselines/`, installed as the package `kgnavbench_baselines`;
  * `./baselines/` of the working directory: drop a file there to add a method of your own;
  * or a module registered under the `kgnavbench.baselines` entry-point group by another package.
It defines

    DESCRIPTION = "one line: what the method is"          # required
    PRIVILEGED = False                                    # optional; True: sees the privileged infos

    @dataclass
    class Config:                                         # optional; its fields are the method's options
        stop_probability: float = 0.1                     #   (`--set stop_probability=0.2`)

    def make_policy(config: Config, spec: PolicySpec) -> Policy   # required

and the policy it returns has two methods:

    reset(agent: str) -> None                             # a new episode begins for this agent
    act(observations: dict[str, dict], infos: dict[str, dict]) -> dict[str, int]
                                                          # one action (0..9) per agent in observations

`observations` and `infos` are exactly what `kgnavbench.env` returns for the live agents, made with
features=True (so observations carry the encoder's `features` and `target_features`), infos without
"state" and "expert_action" unless PRIVILEGED. README.md has a worked example; `baselines/random_walk.py`
is the one to copy.

A policy may also have the batched form, which evaluation then uses instead of act (the learned
policies do: no per-agent dicts; 1.4-1.5x faster for them, docs/speed.md):

    act_batch(agents: list[str], observations, infos) -> np.ndarray   # one action per agent, in order

where `observations[key]` and `infos[key]` are arrays with one row per agent of `agents` (the env's
`observation_arrays()` and `info_arrays()`, the same keys as the dicts).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import importlib.util
import math
import os
import signal
import sys
import threading
import time
import typing
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from types import ModuleType

from .errors import KgnavbenchError
from .files import first_line
from .graph import VIEW_SIZE
from .kitchens import object_types
from .world import ACTIONS

SHIPPED_PACKAGE = "kgnavbench_baselines"  # the repository's baselines/ folder, installed under this name
SOURCE_BASELINES_DIR = Path(__file__).resolve().parent.parent / "baselines"  # a source checkout's
ENTRY_POINT_GROUP = "kgnavbench.baselines"


class PluginError(KgnavbenchError, ValueError):
    """A plugin that is missing, fails to import or breaks the interface; or a bad option."""


# the largest seed of a run or an evaluation: every generator takes it, an evaluation's per-kitchen
# seed (seed * 1000 + the kitchen's index) stays within 64 bits, and torchrun's ranks add 1,000,003 each
MAX_SEED = 2**31 - 1


@dataclass(frozen=True)
class PolicySpec:
    """What a policy may know about the environment before it starts."""

    n_actions: int = len(ACTIONS)
    actions: tuple[str, ...] = ACTIONS
    view_size: int = VIEW_SIZE
    object_types: tuple[str, ...] = ()
    seed: int = 0
    checkpoint: str | None = None  # a trained method's checkpoint (`kgnavbench eval --run DIR`)
    device: str = "cpu"  # where a torch policy should compute: "cpu" or "cuda" (`--device`)

    @staticmethod
    def default(
        seed: int = 0, view_size: int = VIEW_SIZE, checkpoint: str | None = None, device: str = "cpu"
    ) -> PolicySpec:
        return PolicySpec(
            view_size=view_size, object_types=object_types(), seed=seed, checkpoint=checkpoint, device=device
        )


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

    def source_bytes(self) -> bytes:
        """The plugin's source code (its file, or its entry point's module file): part of a run's hash."""
        path = (
            self.source if not self.source.startswith("entry point") else getattr(self.module, "__file__", "")
        )
        try:
            return Path(path).read_bytes()
        except (OSError, TypeError):
            return self.source.encode()

    def make_policy(self, config, spec: PolicySpec):
        policy = guarded(self, "make_policy", self.module.make_policy, config, spec)
        missing = [m for m in ("reset", "act") if not callable(getattr(policy, m, None))]
        if missing:
            raise PluginError(
                f"{self.source}: the policy from make_policy has no {' or '.join(m + '()' for m in missing)} "
                "(see kgnavbench/plugins.py for the interface)"
            )
        return policy


# options that change no weight of a run (how often it keeps snapshots): a run trained with another
# value is the same run to `table --trained` and to an evaluation of its checkpoint
UNWEIGHTED_OPTIONS = ("keep_every",)

import_timeout: float | None = None  # seconds a plugin file's import may take (`methods`: 20)

# How long plugin code may run before kgnavbench says so (every WAIT_NOTE seconds, on stderr) or gives
# up (`step_timeout`, eval's --step-timeout; None: never). Unix timers in the main thread: a plugin
# call made anywhere else is not watched.
WAIT_NOTE = 60.0
step_timeout: float | None = None


class PluginTimeout(PluginError):
    """Plugin code ran past `step_timeout`."""


@contextlib.contextmanager
def watched(source: str, what: str, where: str = "", limit: float | None = None, note: float | None = None):
    """While the block runs (plugin code), say every `note` seconds on stderr that kgnavbench is still
    waiting for `what` of `source` (and `where`: the kitchen and step); past `limit` seconds, raise
    PluginTimeout there: a plugin that never returns ends with one line, not a silent hang.

    The limit holds against plugin code that defeats the signal: a time-out the plugin caught is raised
    again when the block returns, and a watchdog thread ends the process (exit 2, one line on stderr)
    if the block is still running WATCHDOG_GRACE seconds past the limit (the plugin caught the time-out
    and went on, or ignored SIGALRM). A caller's own SIGALRM handler and ITIMER_REAL timer are restored
    afterwards, the timer less the time the block took."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "setitimer"):
        yield
        return
    start = time.monotonic()
    place = f" ({where})" if where else ""
    note = WAIT_NOTE if note is None else note
    message = f"{source}: {what} did not return within {limit:g} s{place}" if limit is not None else ""
    timed_out = []

    def alarm(signum, frame):
        waited = time.monotonic() - start
        if limit is not None and waited >= limit:
            timed_out.append(waited)
            raise PluginTimeout(message)
        print(f"kgnavbench: still waiting for {what} of {source}{place}: {waited:.0f} s", file=sys.stderr)
        signal.setitimer(signal.ITIMER_REAL, _next_alarm(waited, limit, note))

    # the watchdog is set before the alarm can fire and released after it no longer can: an alarm
    # raised inside release() would leave the deadline set on code that returned
    watching = _WATCHDOG.watch(limit + WATCHDOG_GRACE, message) if limit is not None else None
    previous = signal.signal(signal.SIGALRM, alarm)
    callers_timer = signal.setitimer(signal.ITIMER_REAL, _next_alarm(0.0, limit, note))
    try:
        yield
        if timed_out:  # the plugin caught the PluginTimeout and returned anyway
            raise PluginTimeout(message)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        if limit is not None:
            _WATCHDOG.release(watching)
        signal.signal(signal.SIGALRM, previous)
        remaining, interval = callers_timer
        if remaining > 0:  # the caller's timer runs on, less the time the block took (at least 1 ms)
            signal.setitimer(signal.ITIMER_REAL, max(1e-3, remaining - (time.monotonic() - start)), interval)


WATCHDOG_GRACE = 5.0  # seconds past a step's limit before the process is ended (the signal did not work)


class _Watchdog:
    """Ends the process if a watched block has not returned by its deadline: its plugin code defeated
    the time-out (caught PluginTimeout and went on, or ignored SIGALRM). Nothing else can stop Python
    code running in the main thread. One daemon thread serves every block, started at the first: a
    thread per block would cost one thread per plugin call under `--step-timeout`."""

    def __init__(self):
        self.changed = threading.Condition()
        self.deadline: tuple[float, str] | None = None  # (time.monotonic() due, message) of the block
        self.thread: threading.Thread | None = None

    def watch(self, seconds: float, message: str):
        """Watch a block for `seconds` from now, or to an enclosing block's deadline if that comes
        first; returns what `release` restores (the enclosing block's)."""
        with self.changed:
            enclosing, due = self.deadline, (time.monotonic() + seconds, message)
            self.deadline = min(enclosing, due) if enclosing is not None else due
            if self.thread is None or not self.thread.is_alive():
                self.thread = threading.Thread(target=self.run, name="kgnavbench-watchdog", daemon=True)
                self.thread.start()
            self.changed.notify()
        return enclosing

    def release(self, enclosing) -> None:
        with self.changed:
            self.deadline = enclosing
            self.changed.notify()

    def run(self) -> None:
        with self.changed:
            while True:
                if self.deadline is None:
                    self.changed.wait()
                    continue
                due, message = self.deadline
                if time.monotonic() < due:
                    self.changed.wait(due - time.monotonic())
                    continue
                try:
                    print(
                        f"kgnavbench: error: {message}, and it defeated the time-out (caught it or "
                        "ignored SIGALRM): the process ends here",
                        file=sys.stderr,
                        flush=True,
                    )
                finally:  # a closed stderr must not leave the process running
                    os._exit(2)


_WATCHDOG = _Watchdog()


def _new_watchdog_after_fork() -> None:
    """A forked worker gets its own watchdog: the parent's thread is not in it, and its lock may have
    been held at the fork."""
    global _WATCHDOG
    _WATCHDOG = _Watchdog()


os.register_at_fork(after_in_child=_new_watchdog_after_fork)


def _next_alarm(waited: float, limit: float | None, note: float) -> float:
    """Seconds to the next note, or to the limit if that comes first."""
    upcoming = (waited // note + 1) * note - waited
    return max(1e-3, min(upcoming, limit - waited) if limit is not None else upcoming)


def guarded(plugin: Plugin, what: str, function, *args, where: str = ""):
    """Call plugin code; whatever it raises (sys.exit too) becomes a PluginError naming its file. Only
    Ctrl-C goes through untouched. Watched (`watched`): `where` names the kitchen and step."""
    try:
        with watched(plugin.source, what, where, step_timeout):
            return function(*args)
    except KeyboardInterrupt:
        raise
    except PluginError:
        raise
    except KeyError as e:
        if e.args in (("expert_action",), ("state",)) and not plugin.privileged:
            raise PluginError(
                f"{plugin.source}: {what} read infos[{e.args[0]!r}], which only a plugin with "
                "PRIVILEGED = True may read"
            ) from e
        raise PluginError(f"{plugin.source}: {what} failed: KeyError: {first_line(e)}") from e
    except BaseException as e:  # noqa: BLE001 - a plugin's SystemExit must not end the benchmark silently
        raise PluginError(f"{plugin.source}: {what} failed: {type(e).__name__}: {first_line(e)}") from e


@dataclass
class _NoOptions:
    """A plugin without a Config class takes no options."""


def baseline_dirs() -> list[Path]:
    """Folders of plugin files, later ones winning a name: the shipped baselines (installed as the
    `kgnavbench_baselines` package, or the source checkout's baselines/), then ./baselines of the
    working directory, where a researcher drops a plugin of their own."""
    dirs = []
    try:
        spec = importlib.util.find_spec(SHIPPED_PACKAGE)
        dirs += [Path(p) for p in (spec.submodule_search_locations or [])] if spec else []
    except (ImportError, ValueError):
        pass
    dirs += [SOURCE_BASELINES_DIR, Path.cwd() / "baselines"]
    unique: list[Path] = []
    for d in dirs:
        if d.is_dir() and d.resolve() not in [u.resolve() for u in unique]:
            unique.append(d)
    return unique


def plugin_sources() -> dict[str, str]:
    """Method name -> where its plugin comes from (an entry point of another package, or a file)."""
    found = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        found[ep.name] = f"entry point {ep.name} = {ep.value}"
    for folder in baseline_dirs():
        for path in sorted(folder.glob("*.py")):
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
            spec = importlib.util.spec_from_file_location(f"kgnavbench_plugin_{name}", source)
            module = importlib.util.module_from_spec(spec)
            sys.modules[spec.name] = module  # dataclasses look their module up here
            with watched(source, "its import", limit=import_timeout):
                spec.loader.exec_module(module)
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # noqa: BLE001 - sys.exit() at import is a broken plugin, too
        raise PluginError(f"{source}: failed to import: {type(e).__name__}: {first_line(e)}") from e
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
    try:
        return plugin.config_class(**values)
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # noqa: BLE001 - a Config whose __post_init__ rejects a value
        raise PluginError(
            f"{plugin.source}: bad options {options}: {type(e).__name__}: {first_line(e)}"
        ) from e


OPTION_TYPES = (bool, int, float, str)


def _convert(plugin: Plugin, key: str, kind, text):
    """An option's text as its field's type: bool, int, float, str, or one of them `| None` ("none")."""
    if not isinstance(text, str):
        return text
    args = typing.get_args(kind)
    optional = type(None) in args
    if optional:
        rest = [a for a in args if a is not type(None)]
        if len(rest) != 1:
            raise PluginError(f"{plugin.source}: option {key} has type {kind}, which options cannot take")
        if text.lower() == "none":
            return None
        kind = rest[0]
    if kind not in OPTION_TYPES:
        raise PluginError(
            f"{plugin.source}: option {key} has type {kind}; options take bool, int, float, str (or X | None)"
        )
    name = kind.__name__ + (" or none" if optional else "")
    if kind is bool:
        if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
            raise PluginError(f"{plugin.source}: option {key}={text!r} is not a {name} (true/false)")
        return text.lower() in ("true", "1", "yes")
    try:
        value = kind(text)
    except ValueError as e:
        raise PluginError(f"{plugin.source}: option {key}={text!r} is not a {name}") from e
    if kind is float and not math.isfinite(value):
        raise PluginError(f"{plugin.source}: option {key}={text!r} is not a finite number")
    return value


def parse_options(items: list[str]) -> dict[str, str]:
    """['a=1', 'b=x'] -> {'a': '1', 'b': 'x'}."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise PluginError(f"option {item!r} is not KEY=VALUE")
        out[key.strip()] = value.strip()
    return out
