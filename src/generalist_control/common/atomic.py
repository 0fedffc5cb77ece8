"""Publish an output folder atomically; never replace or delete a folder the project did not write.

A stage writes into a staging sibling and swaps it into place; a folder is replaced only if its
:data:`MARKER` lists all it holds (or it holds only the stage's exact names): docs/guarantees.md.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import fnmatch
import json
import logging
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

__all__ = [
    "MARKER",
    "FolderBusy",
    "ForeignDirectoryError",
    "check_replaceable",
    "folder_lock",
    "pid_alive",
    "process_start",
    "publish_directory",
    "recover",
    "staging_directory",
]

#: The file, in every folder a stage publishes, that lists what the stage wrote there.
MARKER = ".gc-outputs.json"
_WRITER = "generalist_control"

#: ``renameat2``'s "current directory" descriptor and exchange flag (Linux ABI).
_AT_FDCWD, _RENAME_EXCHANGE = -100, 2
_UNSUPPORTED = {errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.EXDEV, errno.EPERM}

log = logging.getLogger(__name__)


class ForeignDirectoryError(FileExistsError):
    """An output folder holds files the stage did not write; it is left untouched."""


class FolderBusy(RuntimeError):
    """Another process holds the lock of the output folder (:func:`folder_lock`)."""


#: Exact names a stage wrote before markers: ``None`` (a file) or its sub-folder's file pattern.
Owned = Mapping[str, str | None]


def _entries(path: Path) -> list[tuple[str, str]]:
    """Every entry under ``path`` but the marker: (relative POSIX path, file|dir|link)."""
    out = []
    for root, dirs, files in os.walk(path):
        rel = Path(root).relative_to(path)
        for name in dirs + files:
            full = Path(root) / name
            kind = "link" if full.is_symlink() else "dir" if full.is_dir() else "file"
            out.append(((rel / name).as_posix(), kind))
    return sorted(e for e in out if not e[0].startswith(MARKER))  # and its temporary file


def _listing(entries: list[tuple[str, str]]) -> list[str]:
    """The marker's ``entries``: files by path, folders with a trailing ``/``."""
    return [f"{p}/" if kind == "dir" else p for p, kind in entries]


def _read_marker(path: Path) -> dict[str, Any] | None:
    """The project's marker in ``path``; None if there is none or it is not the project's."""
    try:
        marker = json.loads((path / MARKER).read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(marker, dict) and marker.get("written_by") == _WRITER
    return marker if ok and isinstance(marker.get("entries"), list) else None


def _write_marker(folder: Path, setting: str, **extra: Any) -> None:
    """Record everything now in ``folder`` (the stage's outputs) in its marker, atomically."""
    marker = {"written_by": _WRITER, "setting": setting, **extra}
    marker["entries"] = _listing(_entries(folder))
    tmp = folder / f"{MARKER}.tmp-{os.getpid()}"
    tmp.write_text(json.dumps(marker, indent=1) + "\n")
    os.replace(tmp, folder / MARKER)


def _unlisted(path: Path, marker: Mapping[str, Any]) -> list[str]:
    """Entries of ``path`` its marker does not list (links are never outputs)."""
    listed = set(marker["entries"])
    return [
        p for p, kind in _entries(path) if kind == "link" or _listing([(p, kind)])[0] not in listed
    ]


def _foreign_legacy(path: Path, owned: Owned) -> list[str]:
    """Entries of a folder without a marker that are not the stage's exact names.

    Files a sub-folder's pattern accepts count only beside an exact-named file of the stage.
    """
    bad, by_pattern, exact_file = [], [], False
    for entry in sorted(path.iterdir()):
        if entry.name not in owned or entry.is_symlink():
            bad.append(entry.name)
            continue
        inner = owned[entry.name]
        if inner is None:  # a file of this name belongs here
            exact_file |= entry.is_file()
            bad += [] if entry.is_file() else [entry.name]
        elif not entry.is_dir():
            bad.append(entry.name)  # a folder belongs here
        else:
            for p, kind in _entries(entry):
                name = f"{entry.name}/{p}"
                if kind == "link" or (kind == "file" and not fnmatch.fnmatch(Path(p).name, inner)):
                    bad.append(name)
                elif kind == "file":
                    by_pattern.append(name)
    return sorted(bad + ([] if exact_file else by_pattern))


def _foreign(path: Path, owned: Owned) -> list[str]:
    """Entries of ``path`` that are not outputs of the stage (relative paths, sorted)."""
    if not (path / MARKER).exists() and not (path / MARKER).is_symlink():
        return _foreign_legacy(path, owned)
    marker = None if (path / MARKER).is_symlink() else _read_marker(path)
    if marker is None:
        return [f"{MARKER} (not a record this project wrote)"]
    return _unlisted(path, marker)


def check_replaceable(
    out_dir: str | Path, owned: Owned, setting: str = "the output folder"
) -> None:
    """Raise :class:`ForeignDirectoryError` unless ``out_dir`` may be replaced.

    It may if it holds only outputs of the command whose ``setting`` names it (its marker).
    Call it before any work, so a refused run writes nothing. ``owned``: see :data:`Owned`.
    """
    if any(c in key for key in owned for c in "*?["):
        raise ValueError(f"owned names must be exact names, not patterns: {sorted(owned)}")
    out_dir = Path(out_dir)
    recover(out_dir)
    if out_dir.is_symlink() or (out_dir.exists() and not out_dir.is_dir()):
        raise ForeignDirectoryError(
            f"refusing to write {setting} '{out_dir}': it is a file or a link, not a folder "
            "the project wrote; choose another path"
        )
    if not out_dir.exists():
        return
    bad = _foreign(out_dir, owned)
    if bad:
        shown = ", ".join(bad[:8]) + (f" and {len(bad) - 8} more" if len(bad) > 8 else "")
        raise ForeignDirectoryError(
            f"refusing to replace {setting} '{out_dir}': it holds files this stage did not "
            f"write ({shown}; a stage lists what it wrote in the folder's {MARKER}). Nothing "
            f"was changed. Point {setting} at a new or empty folder (or one this stage wrote "
            "before), or move those files away yourself."
        )
    other = (_read_marker(out_dir) or {}).get("setting", setting)
    if other != setting:
        raise ForeignDirectoryError(
            f"refusing to write {setting} '{out_dir}': it holds the outputs of another "
            f"command ({other}, {MARKER}). Nothing was changed; point {setting} at a new or "
            "empty folder"
        )


def _stat(pid: int) -> list[str] | None:
    """Fields 3.. of ``/proc/<pid>/stat`` (state, ..., start time at [19]); None if absent."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None


def process_start(pid: int) -> str | None:
    """The kernel's start time of process ``pid``, None where unknown."""
    stat = _stat(pid)
    return None if stat is None else stat[19]


def pid_alive(pid: int, start: str | None = None) -> bool:
    """Whether process ``pid`` (started at ``start``, if given) runs on this host, not a zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # it exists, under another user
    stat = _stat(pid)
    if stat is None:
        return True  # no /proc: trust the signal
    return stat[0] != "Z" and (not start or stat[19] == start)  # a zombie, a reused pid


def _leftovers(out_dir: Path, kind: str) -> Iterator[tuple[Path, int]]:
    """The project's leftovers ``.<name>.<kind>-<pid>-...`` beside ``out_dir``, with the pid.

    Only folders whose marker names them as staging or lists all they hold.
    """
    prefix = f".{out_dir.name}.{kind}-"
    for p in out_dir.parent.glob(f"{prefix}*"):
        try:
            pid = int(p.name[len(prefix) :].split("-")[0])
        except ValueError:
            continue
        marker = None if p.is_symlink() or not p.is_dir() else _read_marker(p)
        if marker is None:
            continue
        if marker.get("staging") == p.name or not _unlisted(p, marker):
            yield p, pid


def recover(out_dir: str | Path) -> None:
    """Restore ``out_dir`` from an interrupted two-rename publish; remove dead leftovers."""
    out_dir = Path(out_dir)
    if not out_dir.parent.is_dir():
        return
    olds = sorted(_leftovers(out_dir, "old"), key=lambda item: item[0].stat().st_mtime)
    for path, pid in olds:
        if pid_alive(pid) and pid != os.getpid():
            continue
        if not out_dir.exists():
            os.replace(path, out_dir)  # the old outputs go back where they were
        else:
            shutil.rmtree(path, ignore_errors=True)
    for path, pid in _leftovers(out_dir, "tmp"):
        if not pid_alive(pid):
            shutil.rmtree(path, ignore_errors=True)


def _take(lock: Path, out_dir: Path, wait: bool) -> int:
    """A descriptor of ``lock`` holding its ``flock`` (the file still at its place)."""
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
                if not wait:
                    raise FolderBusy(
                        f"{out_dir} is being written by {holder} ({lock} is held): wait for it "
                        "to end, or write elsewhere"
                    ) from None
                log.warning("%s is being written by %s: waiting for it", out_dir, holder)
                fcntl.flock(fd, fcntl.LOCK_EX)
            with suppress(FileNotFoundError):  # removed by its holder as we waited: retake
                if os.stat(lock).st_ino == os.fstat(fd).st_ino:
                    return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)


@contextmanager
def folder_lock(out_dir: str | Path, who: str, wait: bool = True) -> Iterator[None]:
    """Hold ``.<name>.lock`` beside ``out_dir``: one command at a time writes the folder.

    A second waits (``wait``) or gets :class:`FolderBusy`. The ``flock`` ends with the process
    however it ends; the file and the folders made for it are removed on exit.
    """
    out_dir = Path(out_dir)
    lock = out_dir.parent / f".{out_dir.name}.lock"
    made = [p for p in (lock.parent, *lock.parent.parents) if not p.exists()]
    lock.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = _take(lock, out_dir, wait)
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{who} pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
            yield
        finally:
            lock.unlink(missing_ok=True)
            os.close(fd)
    finally:
        for folder in made:  # deepest first
            try:
                folder.rmdir()
            except OSError:
                break


@contextmanager
def staging_directory(out_dir: str | Path) -> Iterator[Path]:
    """A new temporary sibling of ``out_dir`` (marked as a staging folder); removed on error."""
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(
        tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-{os.getpid()}-", dir=out_dir.parent)
    )
    try:
        _write_marker(staging, "", staging=staging.name)  # how recover() knows it
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2``); False where unsupported."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in _UNSUPPORTED:
        return False
    raise OSError(code, os.strerror(code), str(a), None, str(b))


def publish_directory(
    staging: str | Path, out_dir: str | Path, owned: Owned, setting: str = "the output folder"
) -> Path:
    """Put the finished ``staging`` folder in ``out_dir``'s place; return ``out_dir``.

    Raises
    ------
    ForeignDirectoryError
        If ``out_dir`` now holds anything but the stage's outputs (``staging`` is removed).
    """
    staging, out_dir = Path(staging), Path(out_dir)
    try:
        check_replaceable(out_dir, owned, setting)
        _write_marker(staging, setting)
        if out_dir.exists() and _read_marker(out_dir) is None:
            _write_marker(out_dir, setting)  # a folder from before markers: now recorded
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    os.chmod(staging, 0o755)
    if not out_dir.exists():
        os.replace(staging, out_dir)
    elif _exchange(staging, out_dir):
        shutil.rmtree(staging, ignore_errors=True)  # now holds the previous outputs
    else:
        old = out_dir.with_name(f".{out_dir.name}.old-{os.getpid()}-0")
        os.replace(out_dir, old)
        os.replace(staging, out_dir)
        shutil.rmtree(old, ignore_errors=True)
    return out_dir
