"""One commit per run in an output directory: a lock, a journal, and the recovery of dead runs.

A run that writes a set of outputs (``segment``, ``render``, one case of a batch) holds an
exclusive lock on its output directory from before any work until its outputs are committed
(:func:`locked`): a second run on the same directory is refused at once (exit 5) or, with
``wait``, waits for the first. The outputs are written into a staging directory
``.segsnake-stage-*`` inside the output directory and committed by :func:`commit`:

1. a journal ``.segsnake-journal.json`` naming the staging directory and the files is written
   atomically (temporary file, fsync, rename);
2. the files are renamed into place, one by one;
3. the journal is removed.

A run killed before step 1 leaves its staging directory: the old set is intact (roll back). A run
killed after it leaves the journal: the next run on the directory (it holds the lock, so no live
run owns any staging directory) renames the files the journal names that are still staged (roll
forward), then removes every staging directory (:func:`recover`). Signals are deferred across the
commit (:func:`segsnake.cancel.deferred`). So after any kill, once the next run has taken the lock,
the directory holds the complete old set or the complete new set.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import time
from typing import Callable, Iterator

from segsnake import cancel
from segsnake.errors import OutputError

__all__ = ["JOURNAL", "STAGE_PREFIX", "LEGACY_STAGE_PREFIX", "OutputLock", "locked", "try_lock",
           "recover", "stage_dir", "commit", "fsync_dir", "make_dirs", "remove_empty_dirs"]

JOURNAL = ".segsnake-journal.json"
STAGE_PREFIX = ".segsnake-stage-"
# Staging directories of segsnake before the lock (``tempfile.mkdtemp(prefix=".segsnake-")``):
# removed by recover() too. The batch's lock file starts with ".segsnake-" but is a file.
LEGACY_STAGE_PREFIX = ".segsnake-"
# Seconds between two attempts to take a lock with ``wait``: short, so that Ctrl-C is seen at once.
_POLL_S = 0.05


def make_dirs(out_dir: str) -> list[str]:
    """``makedirs`` that returns the directories it created, outermost first.

    Raises
    ------
    OutputError
        The directory cannot be created (exit 5).
    """
    missing = []
    d = os.path.abspath(out_dir)
    while not os.path.lexists(d):
        missing.append(d)
        parent = os.path.dirname(d)
        if parent == d:
            break
        d = parent
    try:
        os.makedirs(out_dir, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"{out_dir}: exists and is not a directory") from None
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot create the output directory "
                          f"({exc.strerror or exc})") from None
    return missing[::-1]


def remove_empty_dirs(created: list[str]) -> None:
    """Remove the directories of ``created`` (innermost first) that are empty."""
    for d in reversed(created):
        with contextlib.suppress(OSError):
            os.rmdir(d)  # only succeeds when empty: never removes anything else


class OutputLock:
    """An exclusive ``flock`` on an output directory (released by :meth:`release`, or by the
    kernel when the process dies)."""

    def __init__(self, path: str, fd: int, created: list[str]) -> None:
        self.path = path
        self.fd = fd
        self.created = created  # the directories this lock's run created (removed if left empty)

    def release(self, *, remove_if_empty: bool = False) -> None:
        """Unlock; with ``remove_if_empty``, first remove the directories this run created when
        they are empty (a failed run leaves no empty output directory)."""
        if self.fd < 0:
            return
        try:
            if remove_if_empty:
                remove_empty_dirs(self.created)
        finally:
            os.close(self.fd)
            self.fd = -1


def try_lock(out_dir: str) -> OutputLock | None:
    """Lock an existing directory if no other process holds it (None if one does)."""
    import fcntl

    try:
        fd = os.open(out_dir, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return OutputLock(out_dir, fd, [])


def _acquire(out_dir: str, wait: bool) -> OutputLock:
    import fcntl

    while True:
        created = make_dirs(out_dir)
        try:
            fd = os.open(out_dir, os.O_RDONLY | os.O_DIRECTORY)
        except FileNotFoundError:  # removed by the run that held it: create it again
            continue
        except OSError as exc:
            remove_empty_dirs(created)
            raise OutputError(f"{out_dir}: cannot open the output directory "
                              f"({exc.strerror or exc})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputError(f"{out_dir}: cannot lock the output directory "
                                  f"({exc.strerror or exc})") from None
            if not wait:
                raise OutputError(f"{out_dir}: another segsnake run is writing into this output "
                                  f"directory; wait for it to finish or add --wait") from None
            time.sleep(_POLL_S)  # a signal ends the sleep with KeyboardInterrupt
            continue
        # The holder may have removed the directory (its run failed) before we got the lock:
        # the lock is then on a deleted directory, so start again.
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(out_dir))
        except OSError:
            same = False
        if same:
            return OutputLock(out_dir, fd, created)
        os.close(fd)


@contextlib.contextmanager
def locked(out_dir: str, *, wait: bool = False) -> Iterator[OutputLock]:
    """Hold the lock of ``out_dir`` (created if missing) for the block, after :func:`recover`.

    The directories it created are removed at the end if they are empty (a failed run leaves
    no empty output directory).

    Raises
    ------
    OutputError
        Another process holds the lock and ``wait`` is false, or the directory cannot be created
        or locked (exit 5).
    """
    lock = _acquire(out_dir, wait)
    try:
        with cancel.cleanup_on_exit(lambda: _abandon(out_dir, lock.created)):
            recover(out_dir)
            yield lock
    finally:
        lock.release(remove_if_empty=True)


def _abandon(out_dir: str, created: list[str]) -> None:
    """What a run ended at once leaves of its own (:func:`segsnake.cancel.cleanup_on_exit`): its
    staging directories, then the directories it created if they are empty. (Never inside a
    commit: the ending waits for it.)"""
    mine = f"{STAGE_PREFIX}{os.getpid()}-"
    with contextlib.suppress(OSError):
        for name in os.listdir(out_dir):
            if name.startswith(mine):
                shutil.rmtree(os.path.join(out_dir, name), ignore_errors=True)
    remove_empty_dirs(created)


def _is_stage(name: str) -> bool:
    return name.startswith(LEGACY_STAGE_PREFIX) and name != JOURNAL and \
        not name.startswith(JOURNAL)


def recover(out_dir: str) -> dict[str, list[str]]:
    """Finish or undo what dead runs left in ``out_dir`` (the caller holds its lock).

    A journal is rolled forward (its staged files renamed into place), then every staging
    directory is removed.

    Returns
    -------
    dict
        ``rolled_forward``: the files put in place; ``removed``: the staging directories removed.
    """
    done: dict[str, list[str]] = {"rolled_forward": [], "removed": []}
    journal = os.path.join(out_dir, JOURNAL)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(journal + ".tmp")  # a journal never completed: its commit never started
    try:
        with open(journal, encoding="utf-8") as fh:
            entry = json.load(fh)
    except FileNotFoundError:
        entry = None
    except (OSError, ValueError) as exc:
        raise OutputError(f"{journal}: unreadable commit journal ({exc}); remove it and the "
                          f".segsnake-stage-* directories next to it by hand") from None
    if entry is not None:
        stage = os.path.join(out_dir, os.path.basename(str(entry["stage"])))
        for name in entry["names"]:
            src = os.path.join(stage, os.path.basename(name))
            if os.path.lexists(src):
                os.replace(src, os.path.join(out_dir, os.path.basename(name)))
                done["rolled_forward"].append(name)
        for name in entry.get("remove", []):  # earlier outputs the new set does not have
            with contextlib.suppress(FileNotFoundError):
                os.unlink(os.path.join(out_dir, os.path.basename(name)))
        fsync_dir(out_dir)
        os.unlink(journal)
        fsync_dir(out_dir)
    try:
        entries = list(os.scandir(out_dir))
    except OSError:
        return done
    for e in entries:
        if _is_stage(e.name) and e.is_dir(follow_symlinks=False):
            shutil.rmtree(e.path, ignore_errors=True)
            done["removed"].append(e.name)
    return done


def stage_dir(out_dir: str) -> str:
    """A new staging directory in ``out_dir`` (the caller holds its lock).

    Raises
    ------
    OutputError
        It cannot be created (read-only directory, disk full).
    """
    import tempfile

    try:
        return tempfile.mkdtemp(prefix=f"{STAGE_PREFIX}{os.getpid()}-", dir=out_dir)
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot write in the output directory "
                          f"({exc.strerror or exc})") from None


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """Make the renames in directory ``path`` durable (errors ignored: not every filesystem
    can)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _write_journal(out_dir: str, stage: str, names: tuple[str, ...],
                   remove: tuple[str, ...] = ()) -> str:
    journal = os.path.join(out_dir, JOURNAL)
    tmp = journal + ".tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump({"stage": os.path.basename(stage), "names": list(names), "remove": list(remove),
                   "pid": os.getpid()}, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, journal)
    fsync_dir(out_dir)
    return journal


def commit(stage: str, out_dir: str, overwrite: bool, names: tuple[str, ...], *,
           remove: tuple[str, ...] = (),
           on_step: Callable[[str], None] | None = None) -> None:
    """Move the staged files ``names`` into ``out_dir``: all of them, or (on a failure this
    process sees) none; a kill leaves a journal that :func:`recover` completes.

    ``remove`` names earlier outputs that are not part of the new set (a sphere's result
    replacing a cylinder's has no ``profile.csv``): with ``overwrite`` they are removed in the
    same commit, so that the directory never mixes the old set and the new.

    The caller holds the lock. Signals are deferred for the whole commit. Earlier outputs are
    hard-linked (or copied) into the staging directory first, so that a failed rename (an I/O
    error) can put them back.

    ``on_step``, if given, is called with the name of each step (``"journal"``, then each file
    name after its rename, then ``"done"``): the fault-injection test stops the process there.

    Raises
    ------
    OutputError
        An output exists and ``overwrite`` is false (it appeared since the run started: written
        by something other than segsnake, which takes the lock).
    OSError
        A rename failed; the directory is as it was.
    """
    finals = [os.path.join(out_dir, n) for n in names]
    with cancel.deferred():
        if not overwrite:
            for final in finals:
                if os.path.lexists(final):
                    raise OutputError(f"{final}: already exists; use --overwrite to replace it")
        stale = tuple(n for n in remove if overwrite and n not in names
                      and os.path.lexists(os.path.join(out_dir, n)))
        backups: dict[str, str] = {}
        for name, final in zip(names + stale, finals + [os.path.join(out_dir, n) for n in stale]):
            if os.path.lexists(final):
                keep = os.path.join(stage, ".old-" + name)
                try:
                    os.link(final, keep)
                except OSError:
                    shutil.copy2(final, keep)  # filesystems without hard links
                backups[final] = keep
        journal = _write_journal(out_dir, stage, names, stale)
        placed: list[str] = []
        removed: list[str] = []
        try:
            if on_step is not None:
                on_step("journal")
            for name, final in zip(names, finals):
                os.replace(os.path.join(stage, name), final)
                placed.append(final)
                if on_step is not None:
                    on_step(name)
            for name in stale:
                final = os.path.join(out_dir, name)
                os.unlink(final)
                removed.append(final)
        except BaseException:
            for final in removed:
                with contextlib.suppress(OSError):
                    os.replace(backups[final], final)
            for final in reversed(placed):
                with contextlib.suppress(OSError):
                    if final in backups:
                        os.replace(backups[final], final)
                    else:
                        os.unlink(final)
            with contextlib.suppress(OSError):
                os.unlink(journal)
            raise
        fsync_dir(out_dir)  # the renames are durable before the journal goes
        os.unlink(journal)
        fsync_dir(out_dir)
        if on_step is not None:
            on_step("done")
