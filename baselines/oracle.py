"""Oracle: the BFS-optimal expert, then Stop. An upper bound and a check of the metrics.

It reads infos["expert_action"] (the first action, in the paper's order, that brings the agent one
step nearer the target's goal states), so it is PRIVILEGED: it knows the map. It must score SR 100
and SPL 100 under either success rule; anything less is a bug in the benchmark.
"""

DESCRIPTION = "shortest path by BFS over the state graph, then Stop (privileged)"
PRIVILEGED = True


class Oracle:
    def reset(self, agent: str) -> None:
        pass

    def act(self, observations: dict, infos: dict) -> dict:
        return {agent: infos[agent]["expert_action"] for agent in observations}


def make_policy(config, spec) -> Oracle:
    return Oracle()
