"""File I/O: outputs written all or nothing, only over what clflow wrote, one writer a
folder at a time (``writing``, ``record``, ``lock``, ``digest``); users' files read with clear
errors (``reading``); file-system errors in one line (``system_errors``). Checks before the
work are clflow.limits'; what each guarantee covers is docs/architecture.md, "Outputs".

    with output_folder("out"):                   # this run's: other runs are refused
        check_output_folder("out", ENTRIES)      # before the work
        with atomic_dir("out", ENTRIES) as new:  # the whole result, staged
            ...                                  # moved in as one step at the end
    with atomic_path("out/frames.npz") as tmp:   # one file, the same way
        np.savez(tmp, x=x)
"""

from clflow.fileio.digest import content_digest, fingerprint
from clflow.fileio.lock import LOCK_NAME, FolderBusy, folder_lock, wait_for_writers
from clflow.fileio.reading import load_arrays, read_json, read_text
from clflow.fileio.record import WRITTEN_RECORD, derived_folders, is_bookkeeping, read_record
from clflow.fileio.system_errors import FILE_SYSTEM_ERRNOS, describe_os_error
from clflow.fileio.writing import (
    HELD_SIGNALS,
    atomic_dir,
    atomic_path,
    atomic_write_text,
    check_output_file,
    check_output_folder,
    copy_file,
    discard_written,
    output_folder,
    remove_entries,
)

__all__ = [
    "FILE_SYSTEM_ERRNOS",
    "HELD_SIGNALS",
    "LOCK_NAME",
    "WRITTEN_RECORD",
    "FolderBusy",
    "atomic_dir",
    "atomic_path",
    "atomic_write_text",
    "check_output_file",
    "check_output_folder",
    "content_digest",
    "copy_file",
    "derived_folders",
    "describe_os_error",
    "discard_written",
    "fingerprint",
    "folder_lock",
    "is_bookkeeping",
    "load_arrays",
    "output_folder",
    "read_json",
    "read_record",
    "read_text",
    "remove_entries",
    "wait_for_writers",
]
