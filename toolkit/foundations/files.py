"""Reading text files and writing results safely.

* :func:`read_text`: a text file as UTF-8, or one line naming the file and what is wrong (missing, a
  folder, not UTF-8 and where).
* :func:`check_output`: an output path checked *before* any work: it is not an input, it can be
  created (its folder exists or can be made, is writable, is not under a file), it is not a device or a
  folder where a file is wanted, and it exists only with ``force``.
* :func:`staged_file` and :func:`staged_folder`: results written beside their place under a hidden
  temporary name and moved into place in one rename when complete. A run that fails or is interrupted
  leaves the previous results (or none), never a mix; a replaced output folder is replaced as a whole,
  including files the new run does not write.
"""

from __future__ import annotations

import contextlib
import csv
import os
import shutil
import tempfile
from pathlib import Path

from knee.foundations.errors import KneeInputError


def read_text(path, what: str = "file") -> str:
    """The text of ``path`` (UTF-8; a byte-order mark is dropped); :class:`KneeInputError` otherwise."""
    p = Path(path)
    if p.is_dir():
        raise KneeInputError(f"{what} {p} is a folder, not a file")
    if not p.is_file():
        raise KneeInputError(f"{what} {p} not found")
    try:
        data = p.read_bytes()
    except OSError as e:
        raise KneeInputError(f"{p}: cannot read ({e.strerror})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        raise KneeInputError(f"{p}: not UTF-8 text (byte 0x{data[e.start]:02x} on line {line}); save it as "
                             f"UTF-8") from None


def _nearest_existing(p: Path) -> Path:
    a = p
    while not a.exists() and a != a.parent:
        a = a.parent
    return a


def _writable_folder(folder: Path, what: Path) -> None:
    if not folder.is_dir():
        raise KneeInputError(f"cannot write {what}: {folder} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise KneeInputError(f"cannot write {what}: {folder} is not writable ({e.strerror})") from None


def _inside(a: Path, b: Path) -> bool:
    """Whether ``a`` is ``b`` or lies under it."""
    return a == b or b in a.parents


def check_output(path, kind: str, force: bool, inputs=(), flag: str = "--out") -> Path:
    """Check an output before any work starts; returns it as a ``Path``.

    ``kind`` is ``"file"`` or ``"folder"``. Refused, with one line: an output that is, contains or lies
    inside one of ``inputs`` (even with ``force``); a file where a folder is wanted or the reverse, or a
    device; an existing file or non-empty folder without ``force``; a location that cannot be written
    (under a file, a read-only or virtual file system)."""
    p = Path(path)
    r = p.resolve()
    for i in inputs:
        if i is None:
            continue
        ir = Path(i).resolve()
        if r == ir:
            raise KneeInputError(f"{flag} {p} is also an input ({i}); choose a separate output")
        if kind == "folder" and _inside(ir, r):
            raise KneeInputError(f"{flag} {p} holds an input ({i}); choose a separate output")
        if Path(i).is_dir() and _inside(r, ir):
            raise KneeInputError(f"{flag} {p} lies inside the input folder {i}; choose an output outside it")
    if p.exists() or p.is_symlink():
        if kind == "file" and not p.is_file():
            raise KneeInputError(f"{flag} {p} is {'a folder' if p.is_dir() else 'not a regular file'}; "
                                 f"give a file path")
        if kind == "folder" and not p.is_dir():
            raise KneeInputError(f"{flag} {p} exists and is not a folder")
        if not force and (kind == "file" or any(p.iterdir())):
            what = "exists" if kind == "file" else "exists and is not empty"
            raise KneeInputError(f"{flag} {p} {what}; not overwritten (use --force to replace it)")
    _writable_folder(_nearest_existing(p.parent), p)
    return p


def _partial(path: Path, tag: str) -> Path:
    return path.with_name(f".{path.name}.{tag}-{os.getpid()}")


@contextlib.contextmanager
def staged_file(path):
    """Yield a temporary path beside ``path``; on success it replaces ``path`` (one rename), on any
    failure or interruption it is removed and ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _partial(path, "partial")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_records(path, records) -> None:
    """Dict records (the same keys each, the first's giving the columns) as a CSV table at ``path``, written
    whole or not at all (:func:`staged_file`); nothing written when there are none."""
    records = list(records)
    if not records:
        return
    with staged_file(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(records[0]))
        w.writeheader()
        w.writerows(records)


@contextlib.contextmanager
def staged_folder(path):
    """Yield a new temporary folder beside ``path``; on success it takes the place of ``path`` as a whole
    (an existing ``path`` is removed, with any files the new results do not have); on failure or
    interruption it is removed and ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _partial(path, "partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if path.exists():
        old = _partial(path, "old")
        os.rename(path, old)
    try:
        os.rename(tmp, path)
    except BaseException:
        if old is not None:
            os.rename(old, path)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


__all__ = ["read_text", "check_output", "staged_file", "staged_folder"]
