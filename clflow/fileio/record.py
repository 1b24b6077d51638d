"""Each output folder's record of what clflow wrote there, and the check that a write
replaces or removes nothing else.

``FOLDER/.clflow-written.json`` is ``{"files": {relative path: content digest}, "stats":
{relative path: fingerprint}, "moving": {relative path: digest}, "source": folder}``:

- ``files``: every file clflow wrote there, by its content (clflow.fileio.digest); an
  empty folder clflow made is ``"path/": "folder"``;
- ``stats``: each file's fingerprint when it was written, so an unchanged file is known
  without reading it (a fingerprint that differs falls back to the digest);
- ``moving``: a file whose new content was being moved in when the writer stopped: both
  contents count as clflow's until the next write there settles it;
- ``source``: the folder a result was derived from, relative (render4d's).

A command replaces or removes an entry only when every file under it is listed with its
content (:func:`check_output_folder`); links are never listed, so a link is always the
user's. A record that is missing or cannot be read proves nothing, and the refusal says so.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

from clflow.errors import InputError
from clflow.fileio.digest import BOOKKEEPING_PREFIX, content_digest, fingerprint
from clflow.fileio.reading import parse_json

WRITTEN_RECORD = ".clflow-written.json"
#: a folder's entry in the record's files (an empty folder that clflow made)
FOLDER = "folder"


@dataclasses.dataclass
class Record:
    """A folder's written-record (see the module's docstring); ``problem``: why the file on
    disk proves nothing ("" when it was read, "missing", or what is wrong with it)."""

    files: dict[str, str] = dataclasses.field(default_factory=dict)
    stats: dict[str, list[int]] = dataclasses.field(default_factory=dict)
    moving: dict[str, str] = dataclasses.field(default_factory=dict)
    source: str | None = None
    problem: str = ""

    def owns(self, folder: Path, name: str) -> bool:
        """Whether file (or empty folder) ``folder/name`` holds what clflow wrote there."""
        path = folder / name
        if path.is_symlink():
            return False
        if path.is_dir():
            return self.files.get(f"{name}/") == FOLDER
        if name in self.files and self.stats.get(name) == fingerprint(path):
            return True
        known = {self.files.get(name), self.moving.get(name)} - {None}
        return bool(known) and content_digest(path) in known

    def to_json(self) -> dict:
        out: dict = {"files": self.files}
        if self.stats:
            out["stats"] = self.stats
        if self.moving:
            out["moving"] = self.moving
        if self.source is not None:
            out["source"] = self.source
        return out


def read_record(folder: str | os.PathLike) -> Record:
    """``folder``'s written-record (empty, with its problem, when missing or unreadable)."""
    path = Path(folder) / WRITTEN_RECORD
    try:
        data = parse_json(path.read_text())
    except FileNotFoundError:
        return Record(problem="missing")
    except (OSError, ValueError) as exc:
        return Record(problem=f"unreadable: {type(exc).__name__}")
    fields = {"files": dict, "stats": dict, "moving": dict}
    if not isinstance(data, dict) or not all(isinstance(data.get(k, {}), t) for k, t in fields.items()):
        return Record(problem="not a record of clflow's")
    source = data.get("source")
    return Record(
        files={str(k): str(v) for k, v in data.get("files", {}).items()},
        stats={str(k): v for k, v in data.get("stats", {}).items() if isinstance(v, list)},
        moving={str(k): str(v) for k, v in data.get("moving", {}).items()},
        source=source if isinstance(source, str) else None,
    )


def write_record(folder: Path, record: Record, scratch: Path) -> None:
    """Replace ``folder``'s record atomically (a reader sees the old or the new), through a
    temporary in ``scratch`` (a staging folder of clflow's on the same file system), synced."""
    tmp = scratch / WRITTEN_RECORD
    with open(tmp, "w") as fh:
        json.dump(record.to_json(), fh, indent=1, sort_keys=True)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, folder / WRITTEN_RECORD)


def is_bookkeeping(name: str) -> bool:
    """Whether an entry name is one of clflow's own (record, lock, staging), never a result's."""
    return name.startswith(BOOKKEEPING_PREFIX)


def _walk(entry: Path) -> list[Path]:
    """``entry`` and, for a real folder, everything under it that is not a folder with
    entries: files, links (to anything), empty folders, and clflow's bookkeeping folders
    (staging folders a write there left), which are not entered; links are not followed."""
    if entry.is_symlink() or not entry.is_dir():
        return [entry]
    found = []
    for root, dirs, files in os.walk(entry):
        kept = [d for d in dirs if not os.path.islink(os.path.join(root, d)) and not is_bookkeeping(d)]
        found += [Path(root, name) for name in sorted(files + [d for d in dirs if d not in kept])]
        if not dirs and not files:
            found.append(Path(root))
        dirs[:] = kept
    return found


def unowned_files(folder: Path, entry: Path, records: dict[Path, Record] | None = None) -> list[Path]:
    """What of ``entry`` (in ``folder``) no written-record (``folder``'s or one between it
    and the file) lists with its content: the user's files, links and folders. ``records``:
    the records read so far, by folder (shared by the calls of one check)."""
    records = {} if records is None else records
    unowned = []
    for item in _walk(entry):
        if is_bookkeeping(item.name) and not item.is_dir():  # a record, a lock
            continue
        place, owned = item.parent, False
        while not owned:
            if place not in records:
                records[place] = read_record(place)
            record = records[place]
            owned = record.owns(place, item.relative_to(place).as_posix())
            if place == folder:
                break
            place = place.parent
        if not owned:
            unowned.append(item)
    return unowned


def derived_folders(path: Path) -> list[Path]:
    """The folders in ``path`` that clflow derived from what ``path`` holds (their written-record
    names ``path`` as its source, e.g. ``clflow render4d SIM -o SIM/mine``)."""
    if not path.is_dir():
        return []
    return [
        child
        for child in sorted(path.iterdir())
        if child.is_dir()
        and not child.is_symlink()
        and (source := read_record(child).source) is not None
        and (child / source).resolve() == path.resolve()
    ]


def targets(path: Path, entries: tuple[str, ...], *, derived: bool = False) -> list[Path]:
    """The entries of folder ``path`` that glob patterns ``entries`` match (clflow's
    bookkeeping left out), with ``derived`` the folders derived from it."""
    found = {e for pattern in entries for e in path.glob(pattern) if not is_bookkeeping(e.name)}
    return sorted(found | set(derived_folders(path) if derived else []))


def check_output_folder(path: str | os.PathLike, entries: tuple[str, ...], inputs=(), *, derived: bool = False) -> None:
    """Refuse (InputError, one line) a write into folder ``path`` that would replace or
    remove what clflow did not write: ``entries`` are glob patterns of every entry the
    command writes or replaces there (``derived``: also the folders clflow derived from the
    earlier result); an entry's files must all be listed, with their content, in a
    written-record, and none of ``inputs`` (the run's input files) may lie in one. Call it
    before the work; the write checks again."""
    path = Path(path)
    if not path.is_dir():
        return
    found = targets(path, entries, derived=derived)
    for given in inputs:
        source = Path(given).resolve()
        for target in found:
            if source == target.resolve():
                raise InputError(f"{given} is an input of this run and one of its outputs: write elsewhere (-o)")
            if target.resolve() in source.parents:
                raise InputError(
                    f"{given} is an input of this run and lies in {target}, which this run replaces: write "
                    f"elsewhere (-o) or move the input"
                )
    records: dict[Path, Record] = {}
    unowned = [item for target in found for item in unowned_files(path, target, records)]
    if not unowned:
        return
    them = "them" if len(unowned) > 1 else "it"
    names = ", ".join(
        str(f.relative_to(path)) + ("/" if f.is_dir() and not f.is_symlink() else "") for f in unowned[:3]
    )
    names += f" and {len(unowned) - 3} more" if len(unowned) > 3 else ""
    problem = read_record(path).problem
    if problem and problem != "missing":
        raise InputError(
            f"{path}: its record of the files clflow wrote ({WRITTEN_RECORD}) is damaged ({problem}), so "
            f"clflow cannot tell {names} from yours: move what you keep and delete the rest, or write elsewhere (-o)"
        )
    why = f"the folder has no {WRITTEN_RECORD}, the record of clflow's files" if problem else "or which changed since"
    raise InputError(
        f"{path} holds {names}, which clflow did not write ({why}) and this run would replace or remove: "
        f"move {them} or write elsewhere (-o)"
    )


__all__ = [
    "FOLDER",
    "Record",
    "WRITTEN_RECORD",
    "check_output_folder",
    "derived_folders",
    "is_bookkeeping",
    "read_record",
    "targets",
    "unowned_files",
    "write_record",
]
