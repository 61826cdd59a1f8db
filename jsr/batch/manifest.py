"""The manifest of a batch: which sequences to reconstruct, one entry each.

A CSV file with a header row, or a YAML file (a list of mappings, or a mapping whose
``sequences`` is that list), with the keys:

    sequence     the sequence folder, relative to the manifest's folder (or absolute); required
    name         the results subfolder (default: the sequence folder's name); unique
    preset       named intrinsics (as ``jsr reconstruct --preset``)
    start        first frame to use (default 0)
    max_frames   use at most this many frames
    set          config overrides ``section.key=value``, separated by ``;`` (YAML: a list too)

Blank lines and lines starting with ``#`` are skipped in a CSV manifest. A manifest that
cannot be read as a whole (no ``sequence`` column, an unknown column, a number that is not
one, two entries with one name) is an :class:`~jsr.errors.InputError`; a sequence folder that
is missing or unusable is not: that entry fails when it runs, and the others go on.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from jsr.errors import InputError
from jsr.io.text import read_user_text

MANIFEST_KEYS = ("sequence", "name", "preset", "start", "max_frames", "set")


@dataclass(frozen=True)
class BatchEntry:
    """One sequence of a batch: its folder (absolute), results subfolder name, selection and
    config overrides; ``where`` names its place in the manifest for messages."""

    name: str
    sequence: Path
    preset: str | None = None
    start: int = 0
    max_frames: int | None = None
    overrides: tuple[str, ...] = field(default_factory=tuple)
    where: str = ""


def read_manifest(path: Path) -> list[BatchEntry]:
    """The entries of a CSV (``.csv``) or YAML (``.yaml``/``.yml``) manifest, in file order."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"manifest {path} does not exist")
    text = read_user_text(path, "manifest")
    if path.suffix.lower() in (".yaml", ".yml"):
        records = _yaml_records(path, text)
    elif path.suffix.lower() == ".csv":
        records = _csv_records(path, text)
    else:
        raise InputError(f"manifest {path}: give a .csv or a .yaml file")
    if not records:
        raise InputError(f"manifest {path} lists no sequence")
    entries = [_entry(path, where, record) for where, record in records]
    seen: dict[str, str] = {}
    for entry in entries:
        if entry.name in seen:
            raise InputError(f"manifest {path}: {entry.where} and {seen[entry.name]} both write results to "
                             f"'{entry.name}'; give them different names (column 'name')")
        seen[entry.name] = entry.where
    return entries


def _csv_records(path: Path, text: str) -> list[tuple[str, dict]]:
    lines = [(number, line) for number, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        return []
    reader = csv.reader(io.StringIO("\n".join(line for _, line in lines)))
    rows = list(reader)
    header = [column.strip() for column in rows[0]]
    _check_keys(path, header, f"line {lines[0][0]}")
    records = []
    for (number, _), row in zip(lines[1:], rows[1:]):
        if len(row) > len(header):
            raise InputError(f"manifest {path} line {number}: {len(row)} values for {len(header)} columns")
        records.append((f"line {number}", {key: value.strip() for key, value in zip(header, row) if value.strip()}))
    return records


def _yaml_records(path: Path, text: str) -> list[tuple[str, dict]]:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise InputError(f"manifest {path} is not valid YAML: {str(error).splitlines()[0]}") from None
    if isinstance(data, dict) and set(data) == {"sequences"}:
        data = data["sequences"]
    if not isinstance(data, list) or not all(isinstance(item, dict) for item in data):
        raise InputError(f"manifest {path}: give a list of entries with the keys {', '.join(MANIFEST_KEYS)} "
                         "(or a mapping 'sequences:' holding that list)")
    records = []
    for index, item in enumerate(data, start=1):
        _check_keys(path, list(item), f"entry {index}")
        records.append((f"entry {index}", {key: value for key, value in item.items() if value is not None}))
    return records


def _check_keys(path: Path, keys: list[str], where: str) -> None:
    unknown = [key for key in keys if key not in MANIFEST_KEYS]
    if unknown:
        raise InputError(f"manifest {path} {where}: unknown column(s) {', '.join(map(str, unknown))}; the columns "
                         f"are {', '.join(MANIFEST_KEYS)}")
    if "sequence" not in keys:
        raise InputError(f"manifest {path} {where}: no 'sequence' column (the sequence folder of each entry)")


def _entry(path: Path, where: str, record: dict) -> BatchEntry:
    if not str(record.get("sequence", "")).strip():
        raise InputError(f"manifest {path} {where}: no sequence folder given")
    sequence = Path(str(record["sequence"]).strip())
    sequence = sequence if sequence.is_absolute() else (path.parent / sequence)
    sequence = Path(*sequence.absolute().parts)  # absolute, so workers elsewhere read the same folder
    name = str(record.get("name", "")).strip() or sequence.resolve().name
    if name in (".", "..") or "/" in name or "\\" in name:
        raise InputError(f"manifest {path} {where}: name '{name}' is not a folder name")
    overrides = record.get("set", ())
    if isinstance(overrides, str):
        overrides = [item for item in overrides.split(";")]
    elif not isinstance(overrides, (list, tuple)):
        raise InputError(f"manifest {path} {where}: 'set' must be overrides separated by ';' or a list of them")
    return BatchEntry(
        name=name,
        sequence=sequence,
        preset=str(record["preset"]).strip() if record.get("preset") not in (None, "") else None,
        start=_whole_number(path, where, "start", record.get("start", 0), minimum=0),
        max_frames=None if record.get("max_frames") in (None, "") else _whole_number(
            path, where, "max_frames", record["max_frames"], minimum=1),
        overrides=tuple(str(item).strip() for item in overrides if str(item).strip()),
        where=where,
    )


def _whole_number(path: Path, where: str, key: str, value, minimum: int) -> int:
    try:
        number = int(str(value).strip())
    except ValueError:
        raise InputError(f"manifest {path} {where}: {key} must be a whole number, got '{value}'") from None
    if number < minimum:
        raise InputError(f"manifest {path} {where}: {key} must be at least {minimum}, got {number}")
    return number
