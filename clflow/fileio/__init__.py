"""File I/O: outputs written atomically and only over what clflow wrote (``writing``), users'
files read with clear errors (``reading``), file-system errors in one line
(``system_errors``); checks before the work are clflow.limits'.

    with atomic_path("out/frames.npz") as tmp:   # tmp is in the same folder
        np.savez(tmp, x=x)                       # write however you like
    # now out/frames.npz exists, complete; on an exception nothing is left behind
    with atomic_dir("out/render") as tmp:        # a staging folder for out/render
        ...                                      # its entries move into out/render at the end
"""

from clflow.fileio.reading import load_arrays, read_json, read_text
from clflow.fileio.system_errors import FILE_SYSTEM_ERRNOS, describe_os_error
from clflow.fileio.writing import (
    DIGEST_READ_BYTES,
    HELD_SIGNALS,
    WRITTEN_RECORD,
    atomic_dir,
    atomic_path,
    atomic_write_text,
    check_output_folder,
    content_digest,
    derived_folders,
)

__all__ = [
    "DIGEST_READ_BYTES",
    "FILE_SYSTEM_ERRNOS",
    "HELD_SIGNALS",
    "WRITTEN_RECORD",
    "atomic_dir",
    "atomic_path",
    "atomic_write_text",
    "check_output_folder",
    "content_digest",
    "derived_folders",
    "describe_os_error",
    "load_arrays",
    "read_json",
    "read_text",
]
