"""kgnavbench: target-driven visual navigation in the 30 iTHOR kitchens (README.md, DESIGN.md).

Importing the package registers its Gymnasium ids (kgnavbench/vecenv.py, kgnavbench/gymenv.py):
`kgnavbench/FloorPlan1-v0` .. `kgnavbench/FloorPlan30-v0`, `kgnavbench/train-v0`, `kgnavbench/val-v0`,
`kgnavbench/test-v0`. The registration names the entry points as strings, so it imports neither torch
nor the env: the command line starts fast. `kgnavbench.evaluate_policy` (kgnavbench/own_policy.py)
evaluates a policy of your own on Table I's fixed episodes, and raises `kgnavbench.EvalError` (a
ValueError) with one line naming what is wrong; both load on first use.
"""


def __getattr__(name: str):
    if name == "evaluate_policy":  # on first use: importing the package stays light
        from .own_policy import evaluate_policy

        return evaluate_policy
    if name == "EvalError":
        from .weights import EvalError

        return EvalError
    raise AttributeError(f"module 'kgnavbench' has no attribute {name!r}")


def _register_gymnasium_ids() -> None:
    from gymnasium.envs.registration import register, registry

    names = [f"FloorPlan{i}" for i in range(1, 31)] + ["train", "val", "test"]  # kitchens.KITCHEN_NAMES
    for name in names:
        env_id = f"kgnavbench/{name}-v0"
        if env_id not in registry:
            register(
                id=env_id,
                entry_point="kgnavbench.gymenv:NavigationGymEnv",
                vector_entry_point="kgnavbench.vecenv:NavigationVectorEnv",
                kwargs={"kitchens": name},
            )


_register_gymnasium_ids()
