"""Check that a code change leaves the reconstruction output unchanged (for refactors).

    python scripts/same_output.py record REFERENCE_DIR SEQ [SEQ ...] [--jobs 2]
    python scripts/same_output.py compare REFERENCE_DIR SEQ [SEQ ...] [--jobs 2]

``record`` runs ``jsr reconstruct SEQ --save-masks`` for every sequence folder and keeps the
digests of the files a refactor must not change: ``camera.tum``, ``landmarks.csv``, every file
under ``objects/`` and ``masks/`` (``REFERENCE_DIR/<sequence name>.json``). ``compare`` runs
the same again and lists every file whose digest differs, or that one run has and the other
not; it exits 1 when anything differs. Extra ``jsr reconstruct`` options go after ``--``
(for example ``-- --max-frames 60``); they are recorded and must be the same in both runs,
unless ``--other-options`` is given (to check that a new switch, turned off, changes nothing).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

COMPARED = ("camera.tum", "landmarks.csv", "objects", "masks")


def digests(results: Path) -> dict[str, str]:
    """SHA-256 of every compared file of a results folder, by path relative to it."""
    found = {}
    for name in COMPARED:
        path = results / name
        files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
        for file in files:
            found[str(file.relative_to(results))] = hashlib.sha256(file.read_bytes()).hexdigest()
    return found


def run(sequence: Path, options: list[str]) -> dict[str, str]:
    """Digests of a fresh ``jsr reconstruct`` of ``sequence`` with ``options``."""
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "results"
        command = [sys.executable, "-m", "jsr.cli", "reconstruct", str(sequence), "--out", str(out),
                   "--save-masks", "--quiet", *options]
        subprocess.run(command, check=True)
        return digests(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("action", choices=["record", "compare"])
    parser.add_argument("reference", type=Path)
    parser.add_argument("sequences", nargs="+", type=Path)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--other-options", action="store_true", help="compare with a record made with other options")
    # argparse would take the words after "--" for sequences: split them off first
    argv = sys.argv[1:]
    after = argv.index("--") if "--" in argv else len(argv)
    arguments, options = parser.parse_known_args(argv[:after])
    options += argv[after + 1:]
    arguments.reference.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(arguments.jobs) as pool:
        results = list(pool.map(lambda s: run(s, options), arguments.sequences))
    differing = 0
    for sequence, found in zip(arguments.sequences, results):
        record = arguments.reference / f"{sequence.name}.json"
        if arguments.action == "record":
            record.write_text(json.dumps({"options": options, "digests": found}, indent=1))
            print(f"{sequence.name}: {len(found)} files recorded")
            continue
        reference = json.loads(record.read_text())
        if reference["options"] != options and not arguments.other_options:
            print(f"{sequence.name}: recorded with options {reference['options']}, not {options}")
            differing += 1
            continue
        expected = reference["digests"]
        changed = sorted(name for name in set(expected) | set(found) if expected.get(name) != found.get(name))
        differing += bool(changed)
        verdict = "identical" if not changed else f"{len(changed)} files differ: {', '.join(changed[:8])}"
        print(f"{sequence.name}: {len(found)} files, {verdict}")
    return 1 if differing else 0


if __name__ == "__main__":
    sys.exit(main())
