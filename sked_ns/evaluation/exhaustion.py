"""Running out of memory, threads or disk space while a saved run loads, renders or is scored: one `error:` line that
says which ran out and what to do, not a traceback (a library loaded late, mapped with no address space left, too)."""

from __future__ import annotations

import contextlib
import errno
from typing import Iterator, Optional

from sked_ns.errors import SkedUserError, one_line

MEMORY_HINT = "free memory, or raise the process's limit (ulimit -v)"
"""What helps wherever memory or threads ran out: a thread's stack is address space too."""
DISK_HINT = "free space on that disk"
DISK_ERRORS = {errno.ENOSPC, errno.EDQUOT}


def ran_out(error: BaseException) -> Optional[str]:
    """What `error` says ran out: 'GPU memory', 'memory', 'threads' or 'disk space'; None for any other failure."""
    text = str(error).lower()
    if isinstance(error, OSError) and error.errno in DISK_ERRORS:
        return "disk space"
    if isinstance(error, RuntimeError) and "can't start new thread" in text:
        return "threads"
    if isinstance(error, RuntimeError) and "cuda out of memory" in text:  # torch.cuda.OutOfMemoryError
        return "GPU memory"
    if isinstance(error, MemoryError) or (isinstance(error, OSError) and error.errno == errno.ENOMEM):
        return "memory"
    # torch's CPU allocator says so in a RuntimeError; a library mapped with too little address space left, in an
    # ImportError (a shared object's static TLS block is another matter, whatever the memory).
    said = ("can't allocate memory", "cannot allocate memory", "failed to map segment")
    if isinstance(error, (RuntimeError, ImportError, OSError)) and any(words in text for words in said):
        return None if "static tls" in text else "memory"
    return None


def exhaustion_line(doing: str, error: BaseException, memory_fix: str = MEMORY_HINT,
                    disk_fix: str = DISK_HINT) -> Optional[str]:
    """`doing: ran out of <what> (<the error>). <what to do>`, or None when `error` is not an exhaustion."""
    what = ran_out(error)
    if what is None:
        return None
    fix = disk_fix if what == "disk space" else memory_fix
    if what == "threads":
        fix += "; a process may also be held to a number of threads (ulimit -u)"
    if what == "GPU memory":
        fix += "; or pass --device cpu"
    return f"{doing}: ran out of {what} ({type(error).__name__}: {one_line(str(error))[:200]}). {fix[:1].upper()}{fix[1:]}."


@contextlib.contextmanager
def exhaustion_as_error(doing: str, memory_fix: str = MEMORY_HINT, disk_fix: str = DISK_HINT) -> Iterator[None]:
    """Within it, running out of memory, threads or disk space is a SkedUserError naming what was being done
    (`doing`) and what to do; every other failure passes unchanged."""
    try:
        yield
    except SkedUserError:
        raise
    except Exception as error:
        line = exhaustion_line(doing, error, memory_fix, disk_fix)
        if line is None:
            raise
        raise SkedUserError(line) from error
