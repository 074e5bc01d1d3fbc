"""On-disk cache of processed assets: one folder per (inputs, settings) hash, written atomically.

Folders live under `cache_dir`, else `$BULBJAX_CACHE_DIR`, else `~/.cache/bulbjax`; they are
derived data (never written into the repo or the source data folder) and safe to delete.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

CACHE_DIR_ENV = "BULBJAX_CACHE_DIR"
META_FILE = "meta.json"


def cache_root(cache_dir: str | os.PathLike | None = None) -> Path:
    """The cache folder: `cache_dir`, else `$BULBJAX_CACHE_DIR`, else `~/.cache/bulbjax`."""
    if cache_dir is None:
        cache_dir = os.environ.get(CACHE_DIR_ENV) or Path.home() / ".cache" / "bulbjax"
    return Path(cache_dir).expanduser()


def content_key(blobs: list[bytes], settings: dict[str, Any]) -> str:
    """Hex digest of the input files' bytes and the (JSON-able) settings."""
    h = hashlib.sha256()
    for b in blobs:
        h.update(len(b).to_bytes(8, "little"))
        h.update(b)
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()


def read_entry(folder: Path) -> dict[str, Any] | None:
    """Metadata of a complete cache entry, or None when there is none."""
    try:
        return json.loads((folder / META_FILE).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def write_entry(folder: Path, files: dict[str, bytes], meta: dict[str, Any]) -> None:
    """Write `files` and `meta.json` into `folder` all at once: into a temporary sibling, then
    one rename, so readers see either nothing or the whole entry. When another process wins the
    race, its entry is kept."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    tmp.chmod(0o755)  # mkdtemp makes it private; the entry is plain shared data
    try:
        for name, data in files.items():
            (tmp / name).write_bytes(data)
        (tmp / META_FILE).write_text(json.dumps(meta, indent=1, sort_keys=True))
        try:
            os.rename(tmp, folder)
        except OSError:
            if read_entry(folder) is None:  # a broken leftover, not a finished entry: replace it
                shutil.rmtree(folder, ignore_errors=True)
                os.rename(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
