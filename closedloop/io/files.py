"""Files written whole: the output set of one command, atomic writes, and the checks made before any work.

Every command writes its outputs through `atomic_write_text` / `atomic_write`, inside an `OutputSet`
where it writes several files: a reader sees the old set or the new one, never a partial file.
"""

from __future__ import annotations

import errno
import os
import shutil
import stat
import tempfile
import uuid
from contextlib import contextmanager
from contextvars import ContextVar, Token
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

from closedloop.errors import InputError

_STAGE = ".closedloop-"  # prefix of every temporary name beside an output
_active: ContextVar["OutputSet | None"] = ContextVar("closedloop_output_set", default=None)
_inputs: ContextVar["dict[tuple[int, int], str] | None"] = ContextVar("closedloop_inputs", default=None)


def note_input(path: str | Path) -> None:
    """Record `path` as an input of the running command (inside `track_inputs`; elsewhere a no-op):
    `OutputSet` then refuses to publish over it (by inode, links resolved), whichever command wrote it.
    Called by the readers (models, logs, bags, manifests, YAML and JSON files)."""
    seen = _inputs.get()
    if seen is None:
        return
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return
    if stat.S_ISREG(st.st_mode):
        seen.setdefault((st.st_dev, st.st_ino), str(path))


@contextmanager
def track_inputs() -> Iterator[None]:
    """The scope of one command: the inputs its readers note are never overwritten by its outputs."""
    token = _inputs.set({})
    try:
        yield
    finally:
        _inputs.reset(token)


def _input_at(target: Path) -> str | None:
    """The noted input `target` is (same inode, and the input's path still leads there), or None."""
    seen = _inputs.get()
    ident = identity(target)
    if not seen or ident is None or ident not in seen:
        return None
    return seen[ident] if identity(seen[ident]) == ident else None


def identity(path: str | Path) -> tuple[int, int] | None:
    """(device, inode) of the file `path` leads to (links followed), None when there is none."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def same_file(a: str | Path, b: str | Path) -> bool:
    """`a` and `b` are one file (one inode after resolving links: hard links, symlinks, ``./x`` and ``x``)."""
    ia = identity(a)
    return ia is not None and ia == identity(b)


def is_special(path: str | Path) -> bool:
    """`path` exists and is a character or block device, a named pipe or a socket (``/dev/null``, a FIFO)."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def _write_special(path: Path, data: bytes) -> None:
    """Write `data` into a device or named pipe in place (a reader of the pipe gets the bytes)."""
    fd = os.open(path, os.O_WRONLY | getattr(os, "O_NOCTTY", 0))
    try:
        _write_all(fd, data)
    finally:
        os.close(fd)


_signals: list[int] = []  # interrupts received by the running command (`note_signal`)


def note_signal(signum: int) -> None:
    """Record an interrupt (the command line's signal handler calls this): no output set is published
    after it, even where a library caught the exception the handler raised."""
    _signals.append(signum)


def clear_signals() -> None:
    """Forget the interrupts of a previous command (the command line calls this when a command starts)."""
    _signals.clear()


class OutputSet:
    """The files of one command, published together: the old set or the new one, never a temporary file.

    Used as a context manager, every `atomic_write_text` inside the block is staged in memory and the
    whole set is published when the block exits without an exception (nothing is written otherwise):

    1. each file's bytes go into an unnamed file (``O_TMPFILE``) in its target's directory and are
       fsynced, so a process killed at any moment of this step leaves no name behind (where the file
       system has no ``O_TMPFILE``: a hidden staging directory ``.closedloop-<pid>-*`` beside the target,
       removed on any exit, including SIGTERM/SIGINT turned into exceptions by the CLI);
    2. then, in `order` (model first, report or manifest last), each is linked under a temporary name
       and renamed onto its target (two system calls: the only moment a kill can leave a name, or
       leave a new model beside an old report, is a few microseconds wide);
    3. the directories are fsynced.

    With `folder`, every file lies in that folder and the folder is published whole: the files are written
    into a hidden temporary folder beside it (``.NAME.tmp-*``, removed on any exit; one a killed process
    left is removed by `remove_temporaries`), in `order` (a completion record last), and the folder is
    renamed onto `folder`, which must be absent or empty.  A `folder` that another process finished
    meanwhile (it holds the last file of `order`) is kept and the new set discarded.
    """

    def __init__(self, order: list | tuple = (), folder: str | Path | None = None):
        self.order = [_target(p) for p in order if p is not None]
        self.files: dict[Path, bytes] = {}
        self.folder = None if folder is None else Path(folder)
        self._token: Token[OutputSet | None] | None = None

    def add(self, target: str | Path, data: str | bytes) -> None:
        """Stage `data` for `target` (a symlink stands for the file it points to, as a shell's ``>``)."""
        self.files[_target(target)] = data.encode() if isinstance(data, str) else bytes(data)

    def __enter__(self) -> "OutputSet":
        self._token = _active.set(self)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._token is not None:
            _active.reset(self._token)
            self._token = None
        if exc_type is None:
            self.commit()

    def commit(self) -> None:
        """Publish the staged files (class doc); devices and named pipes are written in place, last.

        Refused before anything is written: a target that is one of this run's inputs (`note_input`), and
        any set at all once an interrupt was received (`note_signal`: a library may have swallowed it).
        """
        if _signals:
            raise KeyboardInterrupt
        for t in self.files:
            source = _input_at(t)
            if source is not None:
                raise InputError(
                    f"{t}: refusing to overwrite an input of this run ({source}); choose another output path"
                )
        rank = {p: k for k, p in enumerate(self.order)}
        if self.folder is not None:
            self._publish_folder(sorted(self.files, key=lambda p: rank.get(p, len(rank))))
            return
        special = [t for t in self.files if is_special(t)]
        targets = sorted((t for t in self.files if t not in special), key=lambda p: rank.get(p, len(rank)))
        self._publish(targets)
        for t in sorted(special, key=lambda p: rank.get(p, len(rank))):
            _write_special(t, self.files[t])

    def _publish_folder(self, targets: list[Path]) -> None:
        out = self.folder
        assert out is not None
        where = out.resolve()
        for t in targets:
            if t.resolve().parent != where:
                raise ValueError(f"{t}: not in the folder {out} published whole")
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        try:
            for t in targets:
                with open(tmp / t.name, "wb") as fh:
                    fh.write(self.files[t])
                    fh.flush()
                    os.fsync(fh.fileno())
            _fsync_dir(tmp)
            if out.exists():
                if self.order and (out / self.order[-1].name).exists():  # finished meanwhile: keep that one
                    shutil.rmtree(tmp)
                    return
                if any(out.iterdir()):
                    raise InputError(f"{out}: exists and is not empty; remove it or choose another folder")
                out.rmdir()
            os.rename(tmp, out)
            _fsync_dir(out.parent)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    def _publish(self, targets: list[Path]) -> None:
        # (target, fd of an unnamed file or None for a staged file, the name renamed onto the target)
        staged: list[tuple[Path, int | None, Path]] = []
        stage_dirs: list[Path] = []
        try:
            for t in targets:
                t.parent.mkdir(parents=True, exist_ok=True)
                fd = _unnamed(t.parent)
                if fd is None:  # no O_TMPFILE: a hidden staging directory beside the target
                    d = Path(tempfile.mkdtemp(dir=t.parent, prefix=f"{_STAGE}{os.getpid()}-"))
                    stage_dirs.append(d)
                    tmp = d / t.name
                    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
                    staged.append((t, None, tmp))
                else:  # linked under this name just before the renames
                    staged.append((t, fd, t.parent / f"{_STAGE}{os.getpid()}-{t.name}.tmp"))
                try:
                    _write_all(fd, self.files[t])
                    os.fsync(fd)
                except OSError as exc:  # a full disk, a quota: name the output (nothing is published)
                    raise OSError(exc.errno, exc.strerror, str(t)) from None
                finally:
                    if staged[-1][1] is None:
                        os.close(fd)
            held = _hold_open(targets)  # freeing a replaced file's blocks waits for close()
            try:
                named = []  # every name first, then the renames back to back: the moment of a mix is minimal
                for t, fd, name in staged:
                    if fd is not None:
                        _link_unnamed(fd, name)
                    named.append((name, t))
                for tmp, t in named:
                    os.replace(tmp, t)
            finally:
                for h in held:
                    os.close(h)
            for d in {t.parent for t in targets}:
                _fsync_dir(d)
        finally:
            for _, fd, name in staged:
                if fd is not None:
                    os.close(fd)
                    if name.exists():  # linked, not renamed
                        name.unlink()
            for d in stage_dirs:
                shutil.rmtree(d, ignore_errors=True)


def remove_temporaries(folder: str | Path) -> int:
    """Remove the temporary folders a killed process left beside `folder` (`OutputSet` with a folder);
    how many."""
    folder = Path(folder)
    n = 0
    if folder.parent.is_dir():
        for t in folder.parent.glob(f".{folder.name}.tmp-*"):
            shutil.rmtree(t, ignore_errors=True)
            n += 1
    return n


def _target(path: str | Path) -> Path:
    """The absolute path an output is written to: symlinks followed (a dangling one: its target)."""
    p = Path(path)
    if is_special(p):  # /dev/stdout -> /proc/self/fd/1 -> a pipe: opened by the name given
        return p.absolute()
    try:
        return p.resolve() if p.is_symlink() else p.absolute()
    except (OSError, RuntimeError):  # a symlink loop
        return p.absolute()


def _hold_open(paths: list[Path]) -> list[int]:
    """Read descriptors of the existing `paths`: a rename over a file whose inode is still open is a
    metadata update (~0.05 ms), over a closed one it frees the old blocks first (~4 ms on ext4 with
    discard), which would widen the moment at which a kill leaves a mixed set 100-fold."""
    fds = []
    for p in paths:
        try:
            fds.append(os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0)))
        except OSError:
            pass
    return fds


def _unnamed(directory: Path) -> int | None:
    """An unnamed file in `directory` (Linux ``O_TMPFILE``), or None where the file system has none."""
    flag = getattr(os, "O_TMPFILE", None)
    if flag is None:
        return None
    try:
        return os.open(directory, flag | os.O_WRONLY, 0o666)
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL, errno.ENOENT):
            return None
        raise


def _link_unnamed(fd: int, path: Path) -> None:
    """Give the unnamed file `fd` the name `path`: linkat(AT_SYMLINK_FOLLOW) on /proc/self/fd/N.

    (A `dir_fd` makes CPython call linkat rather than link, which would not follow the magic link.)
    """
    root = os.open("/", os.O_RDONLY)
    try:
        os.link(f"/proc/self/fd/{fd}", path, src_dir_fd=root, follow_symlinks=True)
    finally:
        os.close(root)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_text(path: str | Path, text: str | bytes) -> None:
    """Write `text` to `path` whole: into the active `OutputSet` if there is one, else as a set of one."""
    active = _active.get()
    if active is not None:
        active.add(path, text)
        return
    one = OutputSet()
    one.add(path, text)
    one.commit()


def publish(
    files: Mapping[str | Path, str | bytes], order: Sequence[str | Path | None] = (), folder: str | Path | None = None
) -> None:
    """Write the finished `files` (path -> text or bytes) of one command whole, as one `OutputSet` (in
    `order`; with `folder`, that folder published whole)."""
    out = OutputSet(order=list(order), folder=folder)
    for path, data in files.items():
        out.add(path, data)
    out.commit()


def atomic_write(path: str | Path, writer: Callable[[str], None]) -> None:
    """Call `writer(tmp_path)` on a temporary file beside `path`, then publish it like `atomic_write_text`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    d = tempfile.mkdtemp(dir=path.parent, prefix=f"{_STAGE}{os.getpid()}-")
    try:
        tmp = os.path.join(d, path.name)
        writer(tmp)
        data = Path(tmp).read_bytes()
    finally:
        shutil.rmtree(d, ignore_errors=True)
    atomic_write_text(path, data)


def refuse_overwrite(out: str | Path, *inputs: str | Path | None) -> None:
    """An output must never replace one of the user's inputs: the same file by inode, links resolved
    (``a.csv``, ``./a.csv``, a symlink or a hard link to it all name the input)."""
    for i in inputs:
        if i is not None and same_file(out, i):
            raise InputError(f"{out}: refusing to overwrite an input of this run ({i}); choose another output path")


def check_outputs(
    outputs: Mapping[str, str | Path | None], inputs: Sequence[str | Path | None] = (), directory: bool = False
) -> None:
    """Refuse, before any work, output paths that cannot be written (one line naming the option and path).

    `outputs` maps an option (``--out``) to its path.  Refused: two options naming one file, an input
    file (by inode: `refuse_overwrite`), an existing directory (`directory=False`) or an existing file
    (`directory=True`), a path below a file, a directory where no file can be created (read-only, no
    permission: probed).  A device or named pipe (``/dev/null``, a FIFO) is accepted as a file output
    where it can be opened for writing: it is written in place, never replaced.
    """
    seen: dict[Path, str] = {}
    for opt, out in outputs.items():
        if out is None:
            continue
        p = Path(out)
        r = p.resolve()
        if r in seen:
            raise InputError(f"{opt} {out}: the same file as {seen[r]}; give each output its own path")
        seen[r] = f"{opt} {out}"
        try:
            refuse_overwrite(out, *inputs)
        except InputError as exc:
            raise InputError(f"{opt} {exc}") from None
        if is_special(p):
            if directory:
                raise InputError(f"{opt} {out}: is a device or pipe; give a directory")
            if not os.access(p, os.W_OK):
                raise InputError(f"{opt} {out}: cannot write to this device or pipe (permission denied)")
            continue
        if not directory and p.is_dir():
            raise InputError(f"{opt} {out}: is a directory; give a file name")
        if directory and p.exists() and not p.is_dir():
            raise InputError(f"{opt} {out}: is a file; give a directory")
        anc = p if directory else p.parent
        while not anc.exists() and anc != anc.parent:
            anc = anc.parent
        if not anc.is_dir():
            raise InputError(f"{opt} {out}: '{anc}' is a file, not a directory")
        _probe(anc, f"{opt} {out}")


def _probe(directory: Path, what: str) -> None:
    """Create (and drop) an unnamed file in `directory`: does the file system let us write there?"""
    try:
        fd = _unnamed(directory)
        if fd is None:
            fd, tmp = tempfile.mkstemp(dir=directory, prefix=_STAGE)
            os.unlink(tmp)
        os.close(fd)
    except OSError as exc:
        raise InputError(f"{what}: cannot write in {directory} ({exc.strerror})") from None
