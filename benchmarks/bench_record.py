"""What `bench_throughput.py`'s JSON records about where and how it ran: package versions, the
commit, the device, and the writer that keeps a timestamped and a `latest` copy of the results
current while the run goes on."""

from __future__ import annotations

import importlib.metadata
import json
import os
import platform
import re
import socket
import subprocess
from typing import Any

import jax

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def versions() -> dict[str, str | None]:
    """Installed versions of the packages that matter for the figures."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for pkg in ("jax", "jaxlib", "jax-cuda12-plugin", "jax-cuda12-pjrt", "jax-cuda13-plugin", "jax-cuda13-pjrt",
                "flax", "optax", "numpy",
                "mujoco", "mujoco-mjx", "mujoco-warp", "warp-lang", "torch"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = None
    try:
        import warp

        out["warp"] = warp.__version__
    except Exception:  # noqa: BLE001 - informational only
        out["warp"] = None
    return out


def git_commit() -> str | None:
    """HEAD of the working tree, if it is a git checkout."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip() or None
    except Exception:  # noqa: BLE001 - no git on the device machine is fine
        return None


def device_info() -> dict[str, Any]:
    """JAX's first device and the host."""
    d = jax.devices()[0]
    return {"platform": d.platform, "device_kind": d.device_kind, "num_devices": jax.device_count(),
            "host": socket.gethostname(), "cpu_count": os.cpu_count(),
            "xla_flags": os.environ.get("XLA_FLAGS"), "jax_default_matmul_precision":
            str(jax.config.jax_default_matmul_precision)}


def device_slug(kind: str) -> str:
    """File-name-safe device name, e.g. 'NVIDIA H100 80GB HBM3' -> 'nvidia_h100_80gb_hbm3'."""
    return re.sub(r"[^a-z0-9]+", "_", kind.lower()).strip("_") or "unknown"


class ResultWriter:
    """Holds the result dict and rewrites the timestamped and `latest` JSON files on demand."""

    def __init__(self, out_dir: str, slug: str, stamp: str, results: dict[str, Any]):
        os.makedirs(out_dir, exist_ok=True)
        self.paths = [os.path.join(out_dir, f"throughput_{slug}_{stamp}.json"),
                      os.path.join(out_dir, f"throughput_{slug}_latest.json")]
        self.results = results

    def write(self) -> None:
        text = json.dumps(self.results, indent=2, default=str)
        for path in self.paths:
            tmp = path + ".tmp"
            with open(tmp, "w") as f:
                f.write(text + "\n")
            os.replace(tmp, path)
