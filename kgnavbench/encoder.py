"""Stage 6 — encoder: the frozen view encoder and every state's features, computed once and cached.

Read it top to bottom:

1. `Encoder`: a small CNN over 84x84 RGB views, uint8 (B, 84, 84, 3) or (B, 3, 84, 84), normalised
   inside -> (B, 512) features (ReLU, like the pooled ResNet features the paper freezes), plus the
   pretraining heads: the 125 visible types (multi-label), the camera pitch (4 classes) and whether a
   receptacle is open. `ENCODER_FILE` (`kgnavbench/data/encoder.pt`, committed, fp16 weights with
   its training record) holds the frozen encoder; `load_encoder`, `encoder_hash`.
2. `pretrain_encoder` (`kgnavbench encoder pretrain`): supervised on the views of the 20 training
   kitchens only; validation on the 5 validation kitchens (mean average precision and micro-F1 over
   the 125 types). Deterministic given the seed.
3. `state_features(kitchen)`: every state's view encoded once, (S, 512) float16, cached beside the
   state graph as `<kitchen>-<graph fingerprint>.features-<encoder hash>.npy`, memory-mapped;
   `standardize` scales them with the encoder's statistics of the training kitchens, as the learned
   agents and the vector env's observations see them.
"""

from __future__ import annotations

import hashlib
import io
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .errors import KgnavbenchError
from .files import atomic_write, first_line, require_checksum, write_with_checksum
from .graph import VIEW_SIZE, cache_dir, graph_fingerprint, state_graph
from .kitchens import DATA_DIR, check_name
from .tasks import load_task_file
from .world import PITCHES

FEATURE_DIM = 512
N_TYPES = 125
ENCODER_FILE = DATA_DIR / "encoder.pt"
ENCODER_FORMAT = 1
# Fixed input normalisation of the uint8 views (mean and spread of rendered views, rounded).
PIXEL_MEAN, PIXEL_STD = 0.45, 0.25


class EncoderError(KgnavbenchError, ValueError):
    """A missing or corrupt encoder file, bad views, or pretraining asked to validate on its own data."""


# ------------------------------------------------------------------------------------------------
# 1. The view encoder


class Encoder(nn.Module):
    """84x84 RGB view -> 512 features: the convolutional trunk of the Nature DQN (Mnih et al. 2015:
    8x8 stride 4, 4x4 stride 2, 3x3 stride 1 -> 64 x 7 x 7), the classic encoder of 84x84 frames and
    three times faster to train on CPU than a four-layer stride-2 stack of the same size, then a
    linear layer to 512. The heads are used only in pretraining."""

    def __init__(self, feature_dim: int = FEATURE_DIM, n_types: int = N_TYPES):
        super().__init__()
        self.convs = nn.Sequential(
            nn.Conv2d(3, 32, 8, stride=4),  # 20x20
            nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2),  # 9x9
            nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=1),  # 7x7
            nn.ReLU(),
        )
        self.project = nn.Linear(64 * 7 * 7, feature_dim)
        self.type_head = nn.Linear(feature_dim, n_types)
        self.pitch_head = nn.Linear(feature_dim, len(PITCHES))
        self.open_head = nn.Linear(feature_dim, 1)
        # channels-last convolutions run about twice as fast on CPU, and (B, 84, 84, 3) views
        # permuted to NCHW already have that layout: no copy
        self.convs.to(memory_format=torch.channels_last)

    def forward(self, views: Tensor) -> Tensor:
        """(B, 84, 84, 3) or (B, 3, 84, 84), uint8 or float on the uint8 scale 0..255 -> (B, 512)."""
        if views.dim() != 4 or (views.shape[-1] != 3 and views.shape[1] != 3):
            raise EncoderError(f"views must be (B, H, W, 3) or (B, 3, H, W), got {tuple(views.shape)}")
        x = views.permute(0, 3, 1, 2) if views.shape[-1] == 3 else views
        x = (x.float() * (1 / 255) - PIXEL_MEAN) * (1 / PIXEL_STD)
        x = self.convs(x.contiguous(memory_format=torch.channels_last))
        return F.relu(self.project(x.flatten(1)))

    def predict(self, features: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Pretraining heads: type logits (B, 125), pitch logits (B, 4), open logit (B,)."""
        return self.type_head(features), self.pitch_head(features), self.open_head(features).squeeze(-1)


def save_encoder(encoder: Encoder, path: Path, meta: dict, stats: dict | None = None) -> None:
    """fp16 weights, the feature statistics (`feature_statistics`) and the training record, atomically."""
    payload = {
        "format": ENCODER_FORMAT,
        "state_dict": {k: v.detach().to(torch.float16).contiguous() for k, v in encoder.state_dict().items()},
        "feature_stats": stats or {},
        "meta": meta,
    }
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    atomic_write(Path(path), lambda f: f.write(buffer.getvalue()))


def read_encoder_file(path: Path | str = ENCODER_FILE) -> dict:
    """The payload of an encoder file: {"format", "state_dict", "meta"}; EncoderError if unusable."""
    path = Path(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(payload, dict) or payload.get("format") != ENCODER_FORMAT:
            raise ValueError(f"format {payload.get('format') if isinstance(payload, dict) else '?'!r}")
        if not isinstance(payload.get("state_dict"), dict):
            raise ValueError("no state_dict")
        return payload
    except FileNotFoundError as e:
        raise EncoderError(f"encoder weights {path} are missing; run `make encoder` to train them") from e
    except Exception as e:  # noqa: BLE001 - anything unreadable is reported as corrupt, by name
        raise EncoderError(
            f"encoder weights {path} are corrupt ({type(e).__name__}: {first_line(e)}); run `make encoder`"
        ) from e


def load_encoder(path: Path | str = ENCODER_FILE) -> Encoder:
    """The pretrained encoder, float32, in eval mode. EncoderError naming the file if missing/corrupt."""
    payload = read_encoder_file(path)
    state = payload["state_dict"]
    feature_dim = state["project.weight"].shape[0] if "project.weight" in state else FEATURE_DIM
    # the throwaway initial weights must not draw from torch's global generator: whether a kitchen's
    # features were cached or encoded now (which loads the encoder) must not change a training run's
    # random state (found: a resumed run's checkpoint differed from an unbroken one's on exactly this)
    with torch.random.fork_rng(devices=[]):
        encoder = Encoder(feature_dim=feature_dim)
    try:
        encoder.load_state_dict({k: v.float() for k, v in state.items()})
    except RuntimeError as e:
        raise EncoderError(f"encoder weights {path} do not fit the Encoder ({e}); run `make encoder`") from e
    return encoder.eval()


@torch.no_grad()
def feature_statistics(encoder: Encoder, views: np.ndarray, batch: int = 512) -> dict:
    """Per-dimension mean and spread of the encoder's features over `views` (the training kitchens'):
    the networks see standardized features. Raw ReLU features share a large common part, and an LSTM
    fed them sits for hundreds of updates at the marginal action distribution (measured here)."""
    total = torch.zeros(encoder.project.out_features, dtype=torch.float64)
    square = torch.zeros_like(total)
    for i in range(0, len(views), batch):
        f = encoder(torch.from_numpy(np.array(views[i : i + batch]))).double()
        total += f.sum(0)
        square += (f * f).sum(0)
    mean = total / max(1, len(views))
    std = (square / max(1, len(views)) - mean * mean).clamp_min(0).sqrt()
    return {"mean": mean.float(), "std": std.float()}


def standardize(features, stats: dict) -> Tensor:
    """(..., 512) features -> float32 (f - mean) / max(std, 0.1): dimensions that barely vary in the
    training kitchens are not blown up where they do."""
    f = torch.as_tensor(np.asarray(features, np.float32) if not isinstance(features, Tensor) else features)
    return (f.float() - stats["mean"]) / stats["std"].clamp_min(0.1)


_stats_cache: dict[str, dict] = {}


def _one_torch_thread_after_fork() -> None:
    """In a forked child, torch's OpenMP thread pool is gone, and the first multi-threaded op waits on
    it forever (gymnasium's AsyncVectorEnv forks its workers, which then build the env: measured, a
    hang in `standardize`). One thread runs torch's ops inline; a child that wants more sets it."""
    torch.set_num_threads(1)


os.register_at_fork(after_in_child=_one_torch_thread_after_fork)


def encoder_feature_stats(path: Path | str = ENCODER_FILE) -> dict:
    """The committed encoder's feature statistics {"mean", "std"} (512,) float32."""
    key = encoder_hash(path)
    if key not in _stats_cache:
        stats = read_encoder_file(path).get("feature_stats") or {}
        if not all(
            isinstance(stats.get(k), Tensor) and stats[k].shape == (FEATURE_DIM,) for k in ("mean", "std")
        ):
            raise EncoderError(f"encoder weights {path} have no feature statistics; run `make encoder`")
        _stats_cache[key] = {k: stats[k].float() for k in ("mean", "std")}
    return _stats_cache[key]


_hash_cache: dict[tuple, str] = {}


def encoder_hash(path: Path | str = ENCODER_FILE) -> str:
    """12 hex digits of the SHA-256 of the encoder file's bytes (cached per path, size and mtime)."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError as e:
        raise EncoderError(f"encoder weights {path} are missing; run `make encoder` to train them") from e
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _hash_cache:
        _hash_cache[key] = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
    return _hash_cache[key]


# ------------------------------------------------------------------------------------------------
# 2. Pretraining on the training kitchens' views


@dataclass
class ViewSet:
    """The views of some kitchens with their labels, in memory."""

    views: np.ndarray  # (N, 84, 84, 3) uint8
    types: np.ndarray  # (N, 125) uint8: visible object types
    pitch: np.ndarray  # (N,) int64 index into PITCHES
    opened: np.ndarray  # (N,) float32 1 when a receptacle is open


def load_views(kitchens, root: Path | None = None) -> ViewSet:
    parts = [state_graph(check_name(k), root=root) for k in kitchens]
    return ViewSet(
        views=np.concatenate([np.asarray(g.views) for g in parts]),
        types=np.concatenate([np.asarray(g.object_vectors) for g in parts]),
        pitch=np.concatenate([np.searchsorted(PITCHES, g.pitch) for g in parts]).astype(np.int64),
        opened=np.concatenate([(g.opened >= 0) for g in parts]).astype(np.float32),
    )


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """Average precision of one label column: mean precision at the rank of every positive."""
    order = np.argsort(-scores, kind="stable")
    hits = labels[order].astype(np.float64)
    if hits.sum() == 0:
        return float("nan")
    precision = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    return float((precision * hits).sum() / hits.sum())


@torch.no_grad()
def evaluate_encoder(encoder: Encoder, data: ViewSet, batch: int = 256) -> dict:
    """Mean average precision over the types present in `data`, micro-F1 at probability 0.5, pitch
    accuracy and open accuracy."""
    was_training = encoder.training
    encoder.eval()
    type_scores, pitch_pred, open_scores = [], [], []
    for i in range(0, len(data.views), batch):
        f = encoder(torch.from_numpy(np.ascontiguousarray(data.views[i : i + batch])))
        t, p, o = encoder.predict(f)
        type_scores.append(t.numpy())
        pitch_pred.append(p.argmax(1).numpy())
        open_scores.append(o.numpy())
    encoder.train(was_training)
    scores, labels = np.concatenate(type_scores), data.types.astype(bool)
    present = np.flatnonzero(labels.any(0))
    aps = [average_precision(scores[:, j], labels[:, j]) for j in present]
    predicted = scores > 0
    tp = (predicted & labels).sum()
    f1 = 2 * tp / max(1, predicted.sum() + labels.sum())
    return {
        "mAP": round(float(np.mean(aps)), 4),
        "micro_f1": round(float(f1), 4),
        "types_present": int(len(present)),
        "pitch_accuracy": round(float((np.concatenate(pitch_pred) == data.pitch).mean()), 4),
        "open_accuracy": round(float(((np.concatenate(open_scores) > 0) == (data.opened > 0)).mean()), 4),
        "views": int(len(data.views)),
    }


def subsample(data: ViewSet, n: int | None) -> ViewSet:
    """At most n views, evenly spaced (all of them when n is None)."""
    if n is None or n >= len(data.views):
        return data
    keep = np.linspace(0, len(data.views) - 1, n).round().astype(np.int64)
    return ViewSet(data.views[keep], data.types[keep], data.pitch[keep], data.opened[keep])


def shifted(views: np.ndarray, shift: int, rng: np.random.Generator) -> np.ndarray:
    """Every view moved by up to `shift` pixels each way, edges repeated (DrQ's random shift)."""
    if shift == 0:
        return views
    size = views.shape[1]
    padded = np.pad(views, ((0, 0), (shift, shift), (shift, shift), (0, 0)), mode="edge")
    dy, dx = rng.integers(0, 2 * shift + 1, (2, len(views)))
    return np.stack([p[y : y + size, x : x + size] for p, y, x in zip(padded, dy, dx)])


def pretraining_loss(encoder: Encoder, views: torch.Tensor, train, idx: np.ndarray) -> torch.Tensor:
    """The pretraining loss of a batch: the visible types (BCE summed over the types, mean over the
    batch: a view shows ~3 of 125 types, and a mean over types would drown those few positives next
    to the auxiliary losses), with the camera pitch and the open flag at weight 0.25 each."""
    t_logits, p_logits, o_logits = encoder.predict(encoder(views))
    return (
        F.binary_cross_entropy_with_logits(
            t_logits, torch.from_numpy(train.types[idx]).float(), reduction="sum"
        )
        / len(idx)
        + 0.25 * F.cross_entropy(p_logits, torch.from_numpy(train.pitch[idx]))
        + 0.25 * F.binary_cross_entropy_with_logits(o_logits, torch.from_numpy(train.opened[idx]))
    )


def _train_epoch(
    encoder, optimiser, schedule, train, order, batch_size, shift, shifts, images, train_start, name, log
) -> tuple[float, int]:
    """One epoch over the views of `order`, in batches (each sorted: sequential reads), each shifted
    by up to `shift` pixels; a progress line every 15 s. Returns the summed loss and the images
    trained on so far."""
    encoder.train()
    steps = len(order) // batch_size
    running, last_print = 0.0, time.perf_counter()
    for b in range(steps):
        idx = np.sort(order[b * batch_size : (b + 1) * batch_size])
        views = torch.from_numpy(shifted(train.views[idx], shift, shifts))
        loss = pretraining_loss(encoder, views, train, idx)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        schedule.step()
        images += len(idx)
        running += loss.item()
        if time.perf_counter() - last_print > 15 or b == steps - 1:
            last_print = time.perf_counter()
            rate = images / (last_print - train_start)
            log(f"  {name}  batch {b + 1}/{steps}  loss {running / (b + 1):.4f}  {rate:,.0f} images/s")
    return running, images


def _epoch_record(
    encoder: Encoder, epoch: int, epochs: int, loss: float, train_check, val_check, log
) -> dict:
    """An epoch's line of the training record (its mAP on the check views of both splits), logged."""
    on_train, on_val = evaluate_encoder(encoder, train_check), evaluate_encoder(encoder, val_check)
    log(
        f"epoch {epoch}/{epochs}: mAP {on_train['mAP']:.4f} on {on_train['views']} training views, "
        f"{on_val['mAP']:.4f} on {on_val['views']} validation views (micro-F1 {on_val['micro_f1']:.4f})"
    )
    return {
        "epoch": epoch,
        "train_loss": round(loss, 4),
        "train_mAP": on_train["mAP"],
        "val_mAP": on_val["mAP"],
        "val_micro_f1": on_val["micro_f1"],
    }


def pretrain_encoder(
    kitchens=None,
    epochs: int = 8,
    seed: int = 0,
    out: Path | str | None = ENCODER_FILE,
    samples_per_epoch: int = 16_000,
    batch_size: int = 64,
    lr: float = 1e-3,
    shift: int = 4,
    val_kitchens=None,
    max_val_views: int | None = None,
    root: Path | None = None,
    log=print,
) -> tuple[Encoder, dict]:
    """Train the encoder on the views of `kitchens` (default: the training split) to predict the
    visible types (BCE), with the camera pitch and the open flag as auxiliary targets; views shifted
    by up to `shift` pixels. Each epoch is `samples_per_epoch` views drawn without replacement by a
    generator seeded with (seed, epoch). Progress per epoch on 2,000 views of the training kitchens
    and 3,000 of the validation kitchens (default: the validation split); at the end on all of them
    (at most `max_val_views`, evenly spaced, when given). Saves to `out` (None: do not save) and
    returns the encoder and its training record."""
    splits = load_task_file()["splits"]
    kitchens = list(kitchens or splits["train"])
    val_kitchens = list(val_kitchens or splits["val"])
    if set(kitchens) & set(val_kitchens):
        raise EncoderError(
            f"pretraining and validation kitchens overlap: {set(kitchens) & set(val_kitchens)}"
        )
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    start = time.perf_counter()
    train = load_views(kitchens, root)
    val = subsample(load_views(val_kitchens, root), max_val_views)
    train_check, val_check = subsample(train, 2000), subsample(val, 3000)
    log(
        f"pretrain: {len(train.views)} views of {len(kitchens)} training kitchens, "
        f"{len(val.views)} of {len(val_kitchens)} validation kitchens ({time.perf_counter() - start:.1f} s)"
    )
    torch.manual_seed(seed)
    random_init = evaluate_encoder(Encoder(), val)
    torch.manual_seed(seed)
    encoder = Encoder()
    optimiser = torch.optim.Adam(encoder.parameters(), lr=lr)
    n = min(samples_per_epoch, len(train.views))
    steps_per_epoch = n // batch_size
    total = max(1, epochs * steps_per_epoch)
    # linear warm-up over 100 steps, then cosine decay to zero
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimiser, lambda s: min(1.0, (s + 1) / 100) * 0.5 * (1 + math.cos(math.pi * min(s, total) / total))
    )
    history, images = [], 0
    train_start = time.perf_counter()
    for epoch in range(epochs):
        order = np.random.default_rng([seed, epoch]).permutation(len(train.views))[:n]
        shifts = np.random.default_rng([seed, epoch, 1])
        running, images = _train_epoch(
            encoder, optimiser, schedule, train, order, batch_size, shift, shifts, images, train_start,
            f"epoch {epoch + 1}/{epochs}", log,
        )  # fmt: skip
        loss = running / max(1, steps_per_epoch)
        history.append(_epoch_record(encoder, epoch + 1, epochs, loss, train_check, val_check, log))
    seconds = time.perf_counter() - train_start
    encoder.eval()
    final = evaluate_encoder(encoder, val)
    stats = feature_statistics(encoder, train.views)
    # The record is deterministic (no timings): the same seed and data give the same file and hash.
    meta = {
        "seed": seed,
        "epochs": epochs,
        "samples_per_epoch": n,
        "batch_size": batch_size,
        "lr": lr,
        "shift": shift,
        "images": images,
        "kitchens": kitchens,
        "val_kitchens": val_kitchens,
        "view_fingerprints": {k: graph_fingerprint(k) for k in kitchens + val_kitchens},
        "val": final,
        "val_random_init": random_init,
        "history": history,
        "torch": str(torch.__version__),
    }
    log(
        f"pretrain: {images} images in {seconds:.1f} s ({images / max(seconds, 1e-9):,.0f} images/s); on "
        f"{final['views']} validation views: mAP {final['mAP']:.4f} (random init {random_init['mAP']:.4f}), "
        f"micro-F1 {final['micro_f1']:.4f} (random init {random_init['micro_f1']:.4f}), pitch accuracy "
        f"{final['pitch_accuracy']:.4f}"
    )
    if out is not None:
        save_encoder(encoder, Path(out), meta, stats)
        log(f"pretrain: wrote {out} (hash {encoder_hash(out)})")
    return encoder, meta


# ------------------------------------------------------------------------------------------------
# 3. Per-state features, cached beside the state graph


_encoders: dict[str, Encoder] = {}


def _cached_encoder() -> Encoder:
    key = encoder_hash()
    if key not in _encoders:
        _encoders.clear()
        _encoders[key] = load_encoder()
    return _encoders[key]


def features_path(kitchen: str, root: Path | None = None) -> Path:
    root = Path(root or cache_dir())
    return root / f"{kitchen}-{graph_fingerprint(kitchen)}.features-{encoder_hash()}.npy"


@torch.no_grad()
def encode_views(encoder: Encoder, views: np.ndarray, batch: int = 256) -> np.ndarray:
    """(N, 84, 84, 3) uint8 -> (N, 512) float16."""
    out = np.empty((len(views), encoder.project.out_features), np.float16)
    for i in range(0, len(views), batch):
        out[i : i + batch] = encoder(torch.from_numpy(np.array(views[i : i + batch]))).numpy()
    if not np.isfinite(out).all():
        raise EncoderError("encoded features overflow float16")
    return out


def state_features(kitchen: str, root: Path | None = None) -> np.ndarray:
    """(S, 512) float16 features of every state's view (read-only memmap), from the cache or computed
    now with the committed encoder (and cached, with its sha256 beside it). A cache file that is
    unreadable, has no checksum or does not match it, has the wrong shape or type or holds a number that
    is not finite is rebuilt, never trusted."""
    check_name(kitchen)
    graph = state_graph(kitchen, VIEW_SIZE, root)
    path = features_path(kitchen, root)
    expected = (graph.n_states, FEATURE_DIM)
    if path.exists():
        try:
            require_checksum(path)
            features = np.load(path, mmap_mode="r")
            if features.shape != expected or features.dtype != np.float16:
                raise ValueError(f"{features.dtype} {features.shape}, expected float16 {expected}")
            if not np.isfinite(features).all():
                raise ValueError("they hold numbers that are not finite")
            return features
        except Exception as e:  # noqa: BLE001 - derived data: rebuild whatever is wrong with it
            print(
                f"kgnavbench: cached features {path.name} cannot be trusted ({e}); rebuilding them",
                file=sys.stderr,
            )
    features = encode_views(_cached_encoder(), graph.views)
    write_with_checksum(path, lambda f: np.save(f, features))
    return np.load(path, mmap_mode="r")
