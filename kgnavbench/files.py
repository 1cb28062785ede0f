"""Small helpers every stage shares: atomic writes (with a checksum beside the file where it matters),
the git revision of the checkout and the machine, the first line of an error message, a duration for
progress lines and worker processes that end with their parent. No stage's logic lives here."""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def symbolic_link(path: Path) -> str | None:
    """A line saying that a run's file is a symbolic link, or None: a run's files (weights, their
    checksums, config.json, finished.json, metrics.csv) are read as the files in their folder only, so
    a link cannot pass another run's weights, or any file of the machine, off as this run's."""
    if Path(path).is_symlink():
        return f"{path} is a symbolic link; a run's files are read as files in its folder only"
    return None


def atomic_write(path: Path, content) -> None:
    """Write `content` (bytes, text, or a function save(binary file)) into a unique temporary file beside
    `path`, then rename it over `path`: readers never see half a file, concurrent writers never share a
    temporary file, a failure leaves the old file as it was. The one atomic writer of the package."""
    if isinstance(content, str):
        content = content.encode()
    save = (lambda f: f.write(content)) if isinstance(content, bytes) else content
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            save(f)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# The settings that pick the vector code paths, and with them the floats of a trained run
# (docs/reproducibility.md); the thread count changes the order of a sum.
NUMERICS_ENV = ("MKL_CBWR", "ATEN_CPU_CAPABILITY", "OMP_NUM_THREADS")


# The CPU flags that decide which vector code paths MKL, oneDNN and ATen can take (and with them a
# run's floats): two CPUs with the same model name (a virtual "AMD EPYC") may differ in these.
VECTOR_FLAGS = (
    "avx", "avx2", "fma", "f16c", "avx_vnni", "avx512f", "avx512dq", "avx512bw", "avx512vl",
    "avx512_vnni", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16", "amx_int8",
)  # fmt: skip


def machine() -> dict:
    """The CPU and the numerics a run was computed with, saved beside the git revision in every run
    directory: the same code and seed give other weights on another CPU or under other vector paths
    (docs/reproducibility.md), so a run that differs from its namesake can be told why. Decides
    nothing: it is not part of any run's name."""
    cpu = platform.processor() or platform.machine()
    flags: list[str] | None = None  # unknown off Linux
    try:
        with open("/proc/cpuinfo") as f:
            info = f.read().splitlines()
        cpu = next((line.split(":", 1)[1].strip() for line in info if line.startswith("model name")), cpu)
        have = next((set(line.split(":", 1)[1].split()) for line in info if line.startswith("flags")), set())
        flags = [flag for flag in VECTOR_FLAGS if flag in have]
    except OSError:
        pass  # not Linux: platform's name stays
    record = {
        "cpu": cpu,
        "vector_flags": flags,
        "cores": os.cpu_count(),
        "numerics": {k: os.environ.get(k) for k in NUMERICS_ENV},
    }
    torch = sys.modules.get("torch")  # only where it is loaded: this module never imports it
    if torch is not None:
        record["torch"] = torch.__version__
        record["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
        record["native_bf16"] = bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    return record


def machine_key(record: dict) -> str:
    """What a recording of a run's bytes is kept under: the CPU's model name, its vector flags and
    torch's version ("AMD EPYC | avx avx2 f16c fma | torch 2.13.0"). The numerics are not in it: a
    recording is made under the pinned ones (tests/test_train.py)."""
    flags = record.get("vector_flags")
    torch_version = str(record.get("torch", "?")).split("+")[0]
    return f"{record.get('cpu')} | {' '.join(flags) if flags is not None else '?'} | torch {torch_version}"


def git_revision() -> str:
    """The checkout's commit, saved in every run directory: HEAD's, with '-dirty' when tracked files
    differ from it; 'unknown' outside a checkout."""

    def git(*args: str) -> str:
        out = subprocess.run(
            ["git", *args], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=10
        )
        return out.stdout.strip()

    try:
        rev = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (rev + ("-dirty" if dirty else "")) if rev else "unknown"


def first_line(error: BaseException) -> str:
    """An exception's message cut to its first line (torch's load errors run to a page); an exception
    whose message cannot be made (its __str__ raises) is named as such, never a second traceback."""
    try:
        text = str(error)
    except Exception:  # noqa: BLE001 - a plugin's exception may be anything
        return f"(an unprintable {type(error).__name__})"
    return (text.strip().splitlines() or [""])[0]


def one_line(text: str) -> str:
    """Text as one line of printable characters (control characters, newlines included, become spaces):
    a name or a field put into a message, a table cell or a printed command."""
    return "".join(c if c.isprintable() else " " for c in text)


def duration_text(seconds: float) -> str:
    """A duration for a progress line's ETA: '40 s', '12 min', '2 h 05 min'."""
    seconds = max(0.0, seconds)
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 90 else f"{minutes // 60} h {minutes % 60:02d} min"


def checksum_path(path: Path) -> Path:
    """Where a file's checksum lives: PATH.sha256, in `sha256sum -c`'s format."""
    return path.with_name(f"{path.name}.sha256")


def write_with_checksum(path: Path, content) -> None:
    """Write `content` (bytes, or a function save(binary file) for a large array) atomically and its
    sha256 beside it. The old checksum goes first, so a crash at any moment leaves a file with its own
    checksum or with none, never one with another file's."""
    checksum_path(path).unlink(missing_ok=True)
    atomic_write(path, content)
    digest = hashlib.sha256(content).hexdigest() if isinstance(content, bytes) else sha256_file(path)
    atomic_write(checksum_path(path), f"{digest}  {path.name}\n")


def checksum_matches(path: Path, data: bytes) -> bool | None:
    """Whether data (the bytes read from path) matches the checksum written with it; None where there
    is none (a file written before checksums, or by a writer killed before it wrote one)."""
    try:
        recorded = checksum_path(path).read_text().split()[0]
    except (OSError, UnicodeDecodeError, IndexError):
        return None
    return recorded == hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str:
    """The sha256 of a file's bytes, read in 1 MiB chunks (a cache file may be a 60 MB array)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


_verified: dict[tuple, str] = {}


def file_matches_checksum(path: Path) -> bool | None:
    """Whether the file at `path` still has the content written with its checksum; None where there is
    no checksum. A file verified before in this process, same size and modification time, is not read
    again (a process loads each cached array once, and a second load would cost as much again)."""
    try:
        recorded = checksum_path(path).read_text().split()[0]
        stat = path.stat()
    except (OSError, UnicodeDecodeError, IndexError):
        return None
    key = (str(path), stat.st_size, stat.st_mtime_ns, recorded)
    if key not in _verified:
        _verified[key] = sha256_file(path)
    return _verified[key] == recorded


def require_checksum(path: Path) -> None:
    """Raise ValueError unless the file at `path` matches the checksum written with it (a cache file
    without one, or one that changed since, is not to be trusted)."""
    match = file_matches_checksum(path)
    if not match:
        raise ValueError(
            f"{path.name} " + ("has no checksum" if match is None else "does not match its checksum")
        )


def end_with_parent(parent: int) -> None:
    """A process pool's initializer (`initargs=(os.getpid(),)`): the worker ends as soon as the process
    that started it is gone, killed or not, instead of working on for nobody (a worker is re-parented
    when its parent dies; a daemon thread watches for that)."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="end-with-parent", daemon=True).start()
