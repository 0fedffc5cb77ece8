"""Publish an output folder atomically, and never replace a folder the project did not write.

A stage writes its outputs into a temporary sibling folder (:func:`staging_directory`) and
then swaps it into place (:func:`publish_directory`):

* **Nothing of the user's is deleted.** A folder that already exists is replaced only if
  everything in it is something the stage itself writes (the names and patterns it passes
  as ``owned``); otherwise :class:`ForeignDirectoryError` names the foreign entries and
  nothing is touched. ``paths.data_dir=data`` (a folder with ``.gitignore``) is refused.
* **Never half-written, never missing.** On Linux the two folders are exchanged in one
  ``renameat2(RENAME_EXCHANGE)`` call, so the old outputs are in place until the new ones
  are. Where that call is missing (another OS, an old file system) the old folder is first
  renamed to ``.<name>.old-<pid>`` and the new one renamed into place; a kill between the
  two renames leaves the old folder under that name, and :func:`recover` (called by every
  publish, and by the loaders) moves it back.
* **No clutter.** Staging and old folders of processes that are no longer alive are removed
  at the next publish; ``.gitignore`` ignores ``.*.tmp-*`` and ``.*.old-*``.
"""

from __future__ import annotations

import ctypes
import errno
import fnmatch
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "ForeignDirectoryError",
    "check_replaceable",
    "publish_directory",
    "recover",
    "staging_directory",
]

#: ``renameat2`` flags and the "current directory" file descriptor (Linux ABI).
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2
_UNSUPPORTED = {errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.EXDEV, errno.EPERM}


class ForeignDirectoryError(FileExistsError):
    """An output folder holds files the stage did not write; it is left untouched."""


Owned = Mapping[str, str | None]


def _foreign(path: Path, owned: Owned) -> list[str]:
    """Entries of ``path`` that are not outputs of the stage (relative paths, sorted).

    ``owned`` maps a top-level name (or glob) to ``None`` for a file, or to a glob that
    every file inside that sub-folder must match (e.g. ``{"plots": "*.png"}``).
    """
    bad = []
    for entry in sorted(path.iterdir()):
        key = next((k for k in owned if fnmatch.fnmatch(entry.name, k)), None)
        if key is None:
            bad.append(entry.name)
            continue
        inner = owned[key]
        if inner is None:  # a file belongs here
            if entry.is_dir() or entry.is_symlink():
                bad.append(entry.name)
        elif entry.is_symlink() or not entry.is_dir():
            bad.append(entry.name)  # a folder belongs here
        else:
            bad += [
                f"{entry.name}/{p.relative_to(entry)}"
                for p in sorted(entry.rglob("*"))
                if p.is_symlink() or (not p.is_dir() and not fnmatch.fnmatch(p.name, inner))
            ]
    return bad


def check_replaceable(
    out_dir: str | Path, owned: Owned, setting: str = "the output folder"
) -> None:
    """Raise :class:`ForeignDirectoryError` unless ``out_dir`` may be replaced.

    Call it before any work, so a refused run writes nothing. A missing or empty folder, or
    one holding only the stage's own outputs, may be replaced.
    """
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
            f"write ({shown}). Nothing was changed. Point {setting} at a new or empty folder "
            "(or one this stage wrote before), or move those files away yourself."
        )


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _leftovers(out_dir: Path, kind: str) -> Iterator[tuple[Path, int]]:
    """Sibling folders ``.<name>.<kind>-<pid>-...`` and the pid that made each."""
    for p in out_dir.parent.glob(f".{out_dir.name}.{kind}-*"):
        try:
            pid = int(p.name[len(f".{out_dir.name}.{kind}-") :].split("-")[0])
        except ValueError:
            continue
        yield p, pid


def recover(out_dir: str | Path) -> None:
    """Restore ``out_dir`` from an interrupted two-rename publish; remove dead leftovers."""
    out_dir = Path(out_dir)
    if not out_dir.parent.is_dir():
        return
    olds = sorted(_leftovers(out_dir, "old"), key=lambda item: item[0].stat().st_mtime)
    for path, pid in olds:
        if _alive(pid) and pid != os.getpid():
            continue
        if not out_dir.exists():
            os.replace(path, out_dir)  # the old outputs go back where they were
        else:
            shutil.rmtree(path, ignore_errors=True)
    for path, pid in _leftovers(out_dir, "tmp"):
        if not _alive(pid):
            shutil.rmtree(path, ignore_errors=True)


@contextmanager
def staging_directory(out_dir: str | Path) -> Iterator[Path]:
    """A new temporary sibling of ``out_dir``; removed if the block raises."""
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(
        tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-{os.getpid()}-", dir=out_dir.parent)
    )
    try:
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
    """Put the finished ``staging`` folder in place of ``out_dir`` (see the module docstring).

    Raises
    ------
    ForeignDirectoryError
        If ``out_dir`` holds anything but the stage's own outputs (checked again here, in
        case something appeared while the stage ran); ``staging`` is then removed.
    """
    staging, out_dir = Path(staging), Path(out_dir)
    try:
        check_replaceable(out_dir, owned, setting)
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
