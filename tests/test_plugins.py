"""The plugin interface: discovery, typed options, and clear errors for broken plugins."""

import textwrap

import pytest

from kgnavbench import plugins
from kgnavbench.plugins import PluginError, PolicySpec, load_plugin, parse_options


def test_the_shipped_plugins_load():
    assert {"random_walk", "oracle"} <= set(plugins.available())
    walk = load_plugin("random_walk")
    assert not walk.privileged and walk.description
    assert load_plugin("oracle").privileged


def test_options_are_typed_and_checked():
    walk = load_plugin("random_walk")
    assert walk.config({"stop_probability": "0.25"}).stop_probability == 0.25
    with pytest.raises(PluginError, match="unknown option 'speed'.*stop_probability"):
        walk.config({"speed": "3"})
    with pytest.raises(PluginError, match="stop_probability='fast' is not a float"):
        walk.config({"stop_probability": "fast"})
    with pytest.raises(PluginError, match="random_walk.py: make_policy failed.*stop_probability"):
        walk.make_policy(walk.config({"stop_probability": "2"}), PolicySpec.default())
    assert parse_options(["a=1", "b = x"]) == {"a": "1", "b": "x"}
    with pytest.raises(PluginError, match="KEY=VALUE"):
        parse_options(["novalue"])


def test_random_walk_acts_for_every_agent_and_is_seeded():
    walk = load_plugin("random_walk")
    obs = {f"navigator_{i}": {} for i in range(50)}

    def actions(seed):
        policy = walk.make_policy(walk.config(), PolicySpec.default(seed))
        return [policy.act(obs, {}) for _ in range(3)]

    assert actions(1) == actions(1) != actions(2)
    first = actions(1)[0]
    assert set(first) == set(obs) and all(0 <= a < 10 for a in first.values())


def test_unknown_method_lists_the_available_ones():
    with pytest.raises(PluginError, match="unknown method 'nope'; available: .*random_walk"):
        load_plugin("nope")


BROKEN = {
    "no_policy": ('DESCRIPTION = "x"\n', r"no_policy.py is not a kgnavbench plugin: make_policy"),
    "no_description": ("def make_policy(config, spec):\n    return None\n", r"DESCRIPTION"),
    "import_error": ("import not_a_module_anywhere\n", r"import_error.py: failed to import: ModuleNotFound"),
    "config_not_dataclass": (
        'DESCRIPTION = "x"\nclass Config:\n    pass\ndef make_policy(config, spec):\n    return None\n',
        r"Config must be a @dataclass",
    ),
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_a_broken_plugin_gets_an_error_naming_the_file(local, name):
    source, message = BROKEN[name]
    (local / f"{name}.py").write_text(source)
    with pytest.raises(PluginError, match=message) as e:
        load_plugin(name)
    assert f"{name}.py" in str(e.value)


def test_a_policy_without_act_is_refused(local):
    (local / "lazy.py").write_text(
        textwrap.dedent(
            """
            DESCRIPTION = "a policy that forgot act()"
            class Lazy:
                def reset(self, agent):
                    pass
            def make_policy(config, spec):
                return Lazy()
            """
        )
    )
    plugin = load_plugin("lazy")
    with pytest.raises(PluginError, match=r"lazy.py: the policy from make_policy has no act\(\)"):
        plugin.make_policy(plugin.config(), PolicySpec.default())


def test_a_copied_random_walk_is_a_new_method(local):
    # the README's worked example: copy baselines/random_walk.py, rename, change
    source = (plugins.SOURCE_BASELINES_DIR / "random_walk.py").read_text()
    (local / "never_stop.py").write_text(
        source.replace("stop_probability: float = 0.1", "stop_probability: float = 0.0")
    )
    plugin = load_plugin("never_stop")
    policy = plugin.make_policy(plugin.config(), PolicySpec.default())
    acts = policy.act({f"a{i}": {} for i in range(500)}, {})
    assert 9 not in acts.values()


def test_the_readme_worked_example_runs(local, floorplan1_tasks):
    """README's "Add a plugin": copy baselines/random_walk.py and apply its sed edits (read from the
    README, so that they cannot rot against the file): a plugin that never stops, so never succeeds."""
    import re

    from kgnavbench.evaluate import EvalConfig, evaluate

    readme = (plugins.SOURCE_BASELINES_DIR.parent / "README.md").read_text()
    assert "cp baselines/random_walk.py baselines/never_stop.py" in readme
    text = (plugins.SOURCE_BASELINES_DIR / "random_walk.py").read_text()
    edits = re.findall(r"-e 's/(.+?)/(.*?)/'", readme[readme.index("cp baselines/random_walk.py") :])
    assert len(edits) == 2, edits
    for pattern, replacement in edits:
        text, n = re.subn(pattern, replacement, text, flags=re.M)
        assert n == 1, pattern  # each edit changes the file exactly once
    (local / "never_stop.py").write_text(text)
    plugin = load_plugin("never_stop")
    assert plugin.config({}).stop_probability == 0.0 and "never Stop" in plugin.module.DESCRIPTION
    config = EvalConfig("never_stop", kitchens=("FloorPlan1",), episodes_per_target=1)
    run = evaluate(config, local.parent / "runs", progress=lambda line: None)
    assert run.results and not any(r.success for r in run.results)  # it never stops, so never succeeds
    assert all(r.episode_length == r.max_steps for r in run.results)
