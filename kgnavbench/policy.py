"""Stage 19 — policy: a trained checkpoint as a plugin policy, on what the env shows every plugin.

`load_policy(checkpoint)` is the learned plugins' `make_policy`. The policy reads only the
observations (`features` and `target_features`, the frozen encoder's standardized features of the view
and of the target image, or the views themselves for a pixels model; `view_objects`,
`target_objects`) and the infos' `target` (to run the target's layers once per distinct target) and
`kitchen` (the FF model's scene-specific layer): nothing privileged, no state index. One batched
forward pass over all agents of an `act` call; an LSTM state (or, FF, a history of frames) per agent.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import models
from .agent import Model, rows_of
from .device import DeviceError, resolve
from .kitchens import object_types
from .runs import TrainError, load_checkpoint


class LearnedPolicy:
    """reset(agent) / act(observations, infos) for evaluation (module docstring)."""

    def __init__(self, checkpoint: Path | str, seed: int = 0, device: str = "cpu"):
        ck = load_checkpoint(checkpoint)
        try:
            self.device = resolve(device)
        except DeviceError as e:
            raise TrainError(str(e)) from e
        self.config = models.ModelConfig(**ck["model_config"])
        net = models.make_model(self.config)
        try:
            net.load_state_dict(ck["model"])
        except (RuntimeError, KeyError) as e:
            raise TrainError(f"checkpoint {checkpoint} does not fit its model ({e})") from e
        net.eval().to(self.device)
        covis = models.CoVisibility()
        covis.load_state_dict(ck["covis"])
        self.model = Model(net, self.config, covis, ck["options"].get("bf16", False), self.device)
        with torch.no_grad():
            self.graph = self.model.graph()
        self.training_kitchens = list(ck["kitchens"])
        self.ff = self.config.arch == "ff"
        # what the network looks at: the views for an end-to-end (pixels) model, else their features
        self.view_key, self.target_key = (
            ("view", "target") if self.config.pixels else ("features", "target_features")
        )
        self.generator = torch.Generator(self.device).manual_seed(seed)
        self.slot: dict[str, int] = {}
        self.hidden = None  # (h, c) rows per slot; None for FF
        self.frames: np.ndarray | None = None  # FF: (slots, history, *view) the last frames per slot
        self.fresh: set[str] = set()
        self.type_names = object_types()
        self.attention: tuple[list[str], torch.Tensor] | None = None  # the last act()'s agents, weights

    def reset(self, agent: str) -> None:
        if agent not in self.slot:
            self.slot[agent] = len(self.slot)
            grown = self.model.net.initial_state(len(self.slot), self.device)
            if grown is not None and self.hidden is not None:
                grown = tuple(torch.cat([h, g[len(h) :]]) for h, g in zip(self.hidden, grown))
            self.hidden = grown
        i = self.slot[agent]
        if self.hidden is not None:
            for h in self.hidden:
                h[i] = 0.0
        self.fresh.add(agent)

    def _missing(self, observation) -> None:
        # the keys listed, not `key in observation`: a Mapping's `in` would gather the env's lazy
        # observation arrays (env.BatchObservations) only to test them
        shown = list(observation)
        for key in (self.view_key, self.target_key):
            if key not in shown:
                raise TrainError(
                    f"the observations have no {key!r}: a learned policy needs the env's features "
                    "(parallel_env(..., features=True), as kgnavbench eval makes it)"
                )

    def act(self, observations: dict, infos: dict) -> dict:
        agents = list(observations)
        if not agents:
            return {}
        shown = [observations[a] for a in agents]
        self._missing(shown[0])
        keys = (self.view_key, self.target_key, "view_objects", "target_objects")
        batch = {key: np.stack([o[key] for o in shown]) for key in keys}
        shown_infos = {key: [infos[a][key] for a in agents] for key in ("target", "kitchen")}
        return dict(zip(agents, self.act_batch(agents, batch, shown_infos).tolist()))

    def act_batch(self, agents: list[str], observations, infos) -> np.ndarray:
        """act() on arrays: `observations` and `infos` hold one row per agent of `agents` (the env's
        `observation_arrays()` and `info_arrays()`, or the dicts stacked by act()) -> one action each.
        One batched forward pass, one draw from the policy's generator: the same actions as act()."""
        if not agents:
            return np.zeros(0, np.int64)
        self._missing(observations)
        for a in agents:
            if a not in self.slot:
                self.reset(a)
        slots = np.fromiter((self.slot[a] for a in agents), np.int64, len(agents))
        at = self.model.tensor(slots)  # a tensor index: a NumPy one is converted on every use
        now = observations[self.view_key]
        tensor = self.model.tensor
        r_t = tensor(np.asarray(observations["view_objects"]).astype(np.float32))
        r_g = tensor(np.asarray(observations["target_objects"]).astype(np.float32))
        targets = observations[self.target_key]
        scene, target_rows = None, None
        if self.ff:
            view = tensor(self._frames(agents, slots, now))
            target = tensor(targets)
            scene = np.array([self._scene(k) for k in infos["kitchen"]], np.int64)
        else:  # each distinct target's layers once, with the row of every agent's
            distinct, first, rows = np.unique(
                np.asarray(infos["target"], dtype=object).astype(str), return_index=True, return_inverse=True
            )
            view = tensor(now)
            target = tensor(targets[first])
            target_rows = tensor(rows.reshape(-1))
        self.fresh.difference_update(agents)
        with torch.no_grad():
            logits, _, rows_after, extras = self.model.forward(
                view, target, target_rows, r_t, r_g, rows_of(self.hidden, at), self.graph, scene
            )
            actions = torch.multinomial(F.softmax(logits, -1), 1, generator=self.generator).squeeze(1)
        if self.hidden is not None:
            for h, r in zip(self.hidden, rows_after):
                h[at] = r
        # for recordings (`explain`): kept as the tensor, read only when asked (building per-agent lists
        # on every step cost an evaluation about a seventh of its time)
        self.attention = (agents, extras["attention"]) if extras["attention"] is not None else None
        return actions.cpu().numpy()

    def _frames(self, agents: list[str], slots: np.ndarray, now: np.ndarray) -> np.ndarray:
        """FF: each agent's last `history` frames, this one last (a new episode: this one repeated)."""
        h = self.config.history
        if self.frames is None or len(self.frames) < len(self.slot):
            grown = np.zeros((len(self.slot), h, *now.shape[1:]), now.dtype)
            if self.frames is not None:
                grown[: len(self.frames)] = self.frames
            self.frames = grown
        for j, a in enumerate(agents):
            if a in self.fresh:
                self.frames[self.slot[a]] = now[j]
        self.frames[slots] = np.concatenate([self.frames[slots, 1:], now[:, None]], 1)
        return self.frames[slots]

    def _scene(self, kitchen: str) -> int:
        """The FF model's scene-specific layer: its own for a training kitchen, the first elsewhere."""
        return self.training_kitchens.index(kitchen) if kitchen in self.training_kitchens else 0

    def explain(self, agent: str, top: int = 3) -> dict:
        """What the last act() attended to for this agent: the `top` object types with their weights,
        most attended first, those with weight 0 left out (KG + attention models; an empty list for the
        others, or an agent the last act() did not see)."""
        if self.attention is None or agent not in self.attention[0]:
            return {"attention": []}
        agents, attention = self.attention
        row = attention[agents.index(agent)].float()
        weights, types = row.topk(max(0, min(top, len(row))))
        pairs = zip(types.tolist(), weights.tolist())
        return {"attention": [(self.type_names[t], float(w)) for t, w in pairs if w > 0]}


def load_policy(checkpoint: Path | str | None, seed: int = 0, device: str = "cpu") -> LearnedPolicy:
    """The policy of a trained checkpoint (a learned plugin's make_policy)."""
    if checkpoint is None:
        raise TrainError(
            "this method needs a trained checkpoint: run `kgnavbench train`, then eval --run DIR"
        )
    return LearnedPolicy(checkpoint, seed, device)
