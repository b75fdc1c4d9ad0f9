"""Reading and writing datasets: atomic table writes, atomic directory swaps, content hashes."""
from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import re
import shutil
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

import schemas


def fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_tree(path: Path) -> None:
    """fsync every file and folder under `path` (before renaming it into place as a completion marker)."""
    for p in sorted(path.rglob("*")):
        if p.is_file():
            with open(p, "rb") as fh:
                os.fsync(fh.fileno())
    for d in [path, *(p for p in path.rglob("*") if p.is_dir())]:
        fsync_dir(d)


class WriteError(OSError):
    """An output cannot be written (disk full, read-only folder, a file where a folder should be); the message
    names the file and the cause."""


def write_error(path: Path, err: OSError | None = None) -> WriteError:
    """A WriteError for `path` that says why: from the OS error, or (err None, e.g. an image library that only
    reports failure) from the state of the disk and the folder."""
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    code = err.errno if err is not None else None
    if code is None:
        try:
            if shutil.disk_usage(folder).free < (1 << 20):
                code = errno.ENOSPC
        except OSError:
            pass
        if code is None and folder.is_dir() and not os.access(folder, os.W_OK):
            code = errno.EACCES
    if code in (errno.ENOSPC, errno.EDQUOT):
        why = f"the disk is full (no space left on the device holding {folder}); free some space and rerun"
    elif code in (errno.EACCES, errno.EPERM, errno.EROFS):
        why = f"the folder {folder} is read-only or not writable by this user"
    elif code in (errno.ENOTDIR, errno.EEXIST) or (folder.exists() and not folder.is_dir()):
        why = f"{folder} is a file, not a folder"
    else:
        why = err.strerror if err is not None and err.strerror else "the write failed"
    out = WriteError(code or 0, f"cannot write {path}: {why}; no partial output was kept")
    out.filename = str(path)
    return out


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write to a temp file beside `path`, fsync, rename: readers see the old or the new file, never half.
    A failure (disk full, read-only folder) removes the temp file and raises a WriteError naming `path`."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as err:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise write_error(path, err) from err
    fsync_dir(path.parent)


def write_table(df: pd.DataFrame, path: Path, schema_name: str, metadata: dict[str, str] | None = None) -> None:
    """Validate `df` against its schema and write it atomically as Parquet."""
    table = schemas.validate(df, schema_name)
    if metadata:
        merged = dict(table.schema.metadata or {})
        merged.update({k.encode(): v.encode() for k, v in metadata.items()})
        table = table.replace_schema_metadata(merged)
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    atomic_write_bytes(path, sink.getvalue().to_pybytes())


def read_table(path: Path, schema_name: str) -> pd.DataFrame:
    """Read a Parquet table and check it against its schema (errors name the file)."""
    if not path.is_file():
        raise FileNotFoundError(f"table {path} does not exist")
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as err:
        raise ValueError(f"{path} is not a readable Parquet file: {err}") from err
    df = table.to_pandas()
    try:
        schemas.validate(df, schema_name)
    except schemas.SchemaError as err:
        raise schemas.SchemaError(f"{path}: {err}") from err
    return df


def swap_dir(staging: Path, final: Path) -> None:
    """Move a finished staging folder into place, replacing `final`."""
    final.parent.mkdir(parents=True, exist_ok=True)
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    if final.exists():
        os.replace(final, old)
    os.replace(staging, final)
    fsync_dir(final.parent)
    if old.exists():
        shutil.rmtree(old)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def staging_dir(final: Path) -> Path:
    """A fresh folder beside `final` to build it in (swap_dir moves it into place). Staging folders that
    killed runs left behind (their process is gone) are removed."""
    if final.parent.is_dir():
        for old in final.parent.glob(f".{final.name}.staging-*"):
            pid = old.name.rsplit("-", 1)[-1]
            if pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid)):
                shutil.rmtree(old, ignore_errors=True)
    path = final.with_name(f".{final.name}.staging-{os.getpid()}")
    if path.exists():
        shutil.rmtree(path)
    try:
        path.mkdir(parents=True)
    except OSError as err:
        raise write_error(path, err) from err
    return path


LEFTOVER = re.compile(r"^\..+\.(tmp|staging|old)-(\d+)$")
"""Names of the temp files (atomic_write_bytes) and folders (staging_dir, swap_dir) a run makes."""


def remove_leftovers(roots: list[Path], prefix: str = ".", recursive: bool = True) -> int:
    """Delete temp files and staging/swap folders under `roots` that other processes made (call with the
    row lock held: any such process is gone). Returns how many were removed."""
    n = 0
    for root in roots:
        if not root.is_dir():
            continue
        for parent, dirs, files in os.walk(root):
            for name in list(dirs) + files:
                m = LEFTOVER.match(name)
                if not m or not name.startswith(prefix) or int(m.group(2)) == os.getpid():
                    continue
                path = Path(parent) / name
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path, ignore_errors=True)
                    dirs.remove(name)
                else:
                    path.unlink(missing_ok=True)
                n += 1
            if not recursive:
                break
    return n


class HashCache:
    """Content hashes of files, cached by (size, mtime_ns) so unchanged files are not re-read.

    The hash is of the content; the cache only avoids recomputing it. Stored as JSON.
    """

    def __init__(self, path: Path):
        self.path = path
        self.entries: dict[str, list] = {}
        if path.is_file():
            try:
                self.entries = json.loads(path.read_text())
            except (json.JSONDecodeError, OSError):
                self.entries = {}
        self.dirty = False

    def file_hash(self, path: Path) -> str:
        st = path.stat()
        key = str(path.resolve())
        hit = self.entries.get(key)
        if hit and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            return hit[2]
        h = hashlib.blake2b(digest_size=16)
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        digest = h.hexdigest()
        self.entries[key] = [st.st_size, st.st_mtime_ns, digest]
        self.dirty = True
        return digest

    def tree_hash(self, path: Path) -> str:
        """Hash of a file, or of a folder's relative paths and file contents; '' if missing."""
        if path.is_file():
            return self.file_hash(path)
        if not path.is_dir():
            return ""
        h = hashlib.blake2b(digest_size=16)
        for p in sorted(path.rglob("*")):
            if p.is_file() and not p.name.startswith("."):
                h.update(p.relative_to(path).as_posix().encode())
                h.update(self.file_hash(p).encode())
        return h.hexdigest()

    def save(self) -> None:
        if self.dirty:
            live = {k: v for k, v in self.entries.items() if Path(k).exists()}
            atomic_write_bytes(self.path, json.dumps(live).encode())
            self.dirty = False
