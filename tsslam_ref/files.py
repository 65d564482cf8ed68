"""Writing output files safely: atomic replacement, the user's normal mode, no writing through links.

Every file the package writes into a run folder goes through :func:`atomic_path` (or the two
helpers built on it, :func:`atomic_write_text` and :func:`atomic_write_bytes`):

* the content is written to a new temporary file in the same folder (``.<name>.<random>.tmp``),
  flushed to disk (``fsync``) and then renamed onto the final name with ``os.replace``, so a
  reader sees either the old file or the complete new one, never half a file;
* the new file gets the mode a plain ``open(path, "w")`` would give it (0666 minus the umask),
  not the 0600 of a temporary file;
* a symbolic link that sits at the final name is replaced by the new file: the link goes, its
  target is never opened or changed;
* when writing fails or is interrupted, the temporary file is removed; a file left by a killed
  process is removed by :func:`remove_stray_temporaries` the next time a run uses the folder.

Layer 0 (base): standard library only.
"""

import contextlib
import os
import re
import tempfile
from pathlib import Path
from typing import Callable, Iterator, List, Union

PathLike = Union[str, os.PathLike]

_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp$")
"""Names of our temporary files: ``.<name>.<8 random characters>.tmp``, hidden and named after the
output they were to become (a user's ``tmp12345678.tmp`` is not ours)."""


def normal_mode() -> int:
    """The permission bits ``open(path, "w")`` gives a new file: 0o666 without the process umask."""
    return 0o666 & ~_umask()


def normal_folder(path: PathLike) -> Path:
    """Give ``path`` (a folder made by ``tempfile.mkdtemp``, always 0o700) the mode ``mkdir`` gives:
    0o777 without the umask, so a dataset moved into place is as readable as any other folder."""
    os.chmod(path, 0o777 & ~_umask())
    return Path(path)


def _umask() -> int:
    mask = os.umask(0o022)  # reading the umask means setting it; put it straight back
    os.umask(mask)
    return mask


class OutputWriteError(OSError):
    """Writing an output file failed (a full disk, permissions changed): the file is named, its
    ``errno`` is the cause's, and whatever was at the final name is left as it was."""


@contextlib.contextmanager
def atomic_path(path: PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it becomes ``path`` atomically.

    The caller writes the whole content to the yielded path (any writer that takes a file name:
    ``savefig``, ``torch.save``, ...).  On leaving the block the file is flushed to disk, given
    the normal mode (:func:`normal_mode`) and renamed onto ``path``, replacing a file or a
    symbolic link of that name (never writing through the link).  On an exception (Ctrl-C
    included) the temporary file is removed and ``path`` is left as it was.

    Raises:
        IsADirectoryError: ``path`` is a folder (not a link to one).
        FileNotFoundError: the folder ``path`` would go into does not exist.
        OutputWriteError: an OSError while writing, naming ``path``.
    """
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        raise IsADirectoryError(f"{path}: is a folder, expected a file name to write")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: the folder {path.parent} does not exist")
    # the folder as the system finds it: mkstemp would drop a 'link/..' as text and miss the real folder
    folder = os.path.realpath(path.parent)
    temporary = None
    try:
        handle, temporary = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
        os.close(handle)
        yield Path(temporary)
        with open(temporary, "rb+") as stream:
            os.fsync(stream.fileno())
        os.chmod(temporary, normal_mode())
        os.replace(temporary, path)
    except BaseException as error:
        with contextlib.suppress(FileNotFoundError, TypeError):  # TypeError: mkstemp itself failed
            os.unlink(temporary)
        if isinstance(error, OSError) and not isinstance(error, OutputWriteError):
            reason = f"writing {path} failed: {error.strerror or error}"
            written = OutputWriteError(reason) if error.errno is None else OutputWriteError(error.errno, reason)
            raise written from error
        raise


def atomic_write_bytes(path: PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`); returns ``path``."""
    with atomic_path(path) as temporary:
        temporary.write_bytes(data)
    return Path(path)


def atomic_write_text(path: PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`); returns ``path``."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def is_temporary_of(name: str, is_output: Callable[[str], bool]) -> bool:
    """Whether ``name`` is one of our temporary files for an output that ``is_output`` accepts."""
    match = _TEMPORARY.match(name)
    if match is None:
        return False
    return is_output(match.group("name"))


def remove_stray_temporaries(folder: PathLike, is_output: Callable[[str], bool]) -> List[Path]:
    """Remove our temporary files left in ``folder`` by a killed process.

    Removed are plain files (or links, which are unlinked, never followed) named
    ``.<name>.<8 random characters>.tmp`` where ``is_output(name)`` is true.  Anything else is
    left alone.  Returns the removed paths.
    """
    removed = []
    folder = Path(folder)
    if not folder.is_dir():
        return removed
    for entry in sorted(folder.iterdir()):
        if is_temporary_of(entry.name, is_output) and (entry.is_symlink() or entry.is_file()):
            entry.unlink()
            removed.append(entry)
    return removed
