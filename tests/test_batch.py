"""jsr batch: manifests, a batch on a local Dask cluster against serial runs, reruns, failures
and a stop."""

import hashlib
import io
import json
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from jsr.batch.manifest import read_manifest
from jsr.batch.run import run_batch
from jsr.batch.task import BatchSettings
from jsr.cli import app
from jsr.errors import InputError

runner = CliRunner()
FRAMES = 4
COARSE_MESH = ["--set", "output.mesh_voxel_size=0.05"]
"""Every run of these tests fuses its meshes at 5 cm: at 1 cm the TSDF takes most of a short run's time."""
VOLATILE_SUMMARY_KEYS = ("seconds", "fps", "timings", "output", "platform")
"""What summary.json says about the run's timing and place, not about its results."""


# ------------------------------------------------------------------------------ manifests


def test_csv_and_yaml_manifests_give_the_same_entries(tmp_path):
    (tmp_path / "data" / "kitchen").mkdir(parents=True)
    (tmp_path / "m.csv").write_text(
        "# sequences of the week\nsequence,name,preset,start,max_frames,set\n"
        "data/kitchen,,,,,\n"
        "\n"
        "data/kitchen, fast ,tum-fr1,10,200,ransac.min_matches=12; seed=3\n")
    (tmp_path / "m.yaml").write_text(
        "sequences:\n  - sequence: data/kitchen\n"
        "  - {sequence: data/kitchen, name: fast, preset: tum-fr1, start: 10, max_frames: 200,\n"
        "     set: [ransac.min_matches=12, seed=3]}\n")
    from_csv, from_yaml = read_manifest(tmp_path / "m.csv"), read_manifest(tmp_path / "m.yaml")
    assert [(e.name, e.sequence, e.preset, e.start, e.max_frames, e.overrides) for e in from_csv] == \
        [(e.name, e.sequence, e.preset, e.start, e.max_frames, e.overrides) for e in from_yaml]
    first, second = from_csv
    assert first.name == "kitchen" and first.sequence == tmp_path / "data" / "kitchen"
    assert first.start == 0 and first.max_frames is None and first.overrides == ()
    assert (second.name, second.preset, second.start, second.max_frames) == ("fast", "tum-fr1", 10, 200)
    assert second.overrides == ("ransac.min_matches=12", "seed=3")


@pytest.mark.parametrize("text, fragment", [
    ("name\nx\n", "no 'sequence' column"),
    ("sequence,frames\nx,3\n", "unknown column(s) frames"),
    ("sequence,start\nx,two\n", "start must be a whole number"),
    ("sequence,max_frames\nx,0\n", "max_frames must be at least 1"),
    ("sequence\na/x\nb/x\n", "both write results to 'x'"),
    ("sequence\n", "lists no sequence"),
])
def test_bad_manifests_are_one_clear_error(tmp_path, text, fragment):
    (tmp_path / "m.csv").write_text(text)
    with pytest.raises(InputError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        read_manifest(tmp_path / "m.csv")


# ------------------------------------------------------------------------------- the batch


@pytest.fixture(scope="module")
def sequences(tmp_path_factory, synth_sequence):
    """A folder holding a manifest's sequences: three small synthetic sequences, made of the
    session's synthetic sequence (160x120, one jumping object) cut at frames 0, 5 and 10 by
    the manifests' ``start`` (writing three more costs seconds each)."""
    root = tmp_path_factory.mktemp("batch_sequences")
    (root / "seq").symlink_to(synth_sequence, target_is_directory=True)
    return root


def digests(results: Path) -> dict[str, str]:
    """SHA-256 of every file of a results folder but timings.csv (times), with summary.json
    compared without its timing and output-path keys."""
    found = {}
    for path in sorted(p for p in results.rglob("*") if p.is_file()):
        name = str(path.relative_to(results))
        if name == "timings.csv":
            continue
        data = path.read_bytes()
        if name == "summary.json":
            summary = json.loads(data)
            data = json.dumps({k: v for k, v in summary.items() if k not in VOLATILE_SUMMARY_KEYS}).encode()
        found[name] = hashlib.sha256(data).hexdigest()
    return found


def test_batch_on_a_local_cluster_equals_serial_runs_records_failures_and_skips_on_rerun(sequences, tmp_path):
    manifest = sequences / "manifest.csv"
    manifest.write_text("sequence,name,start,max_frames,set\n"
                        f"seq,a,0,{FRAMES},\n"
                        f"seq,b,5,{FRAMES},seed=4\n"
                        "missing,broken,,,\n"
                        f"seq,c,10,{FRAMES},objects.enabled=true;ransac.min_matches=10\n")
    out = tmp_path / "batch"
    result = runner.invoke(app, ["batch", str(manifest), "--out", str(out), "--workers", "2", "--save-masks",
                                 *COARSE_MESH])
    assert result.exit_code == 3, result.output  # some sequence failed
    assert "failed broken" in result.output and "does not exist" in result.output
    rows = {row["name"]: row for row in json.loads((out / "batch_summary.json").read_text())["sequences"]}
    assert {name: row["status"] for name, row in rows.items()} == {
        "a": "complete", "b": "complete", "broken": "failed", "c": "complete"}
    assert "missing does not exist" in rows["broken"]["error"]
    assert rows["a"]["frames"] == FRAMES and rows["a"]["ate_rmse_cm"] is not None  # evaluated: it has ground truth
    csv_text = (out / "batch_summary.csv").read_text()
    assert csv_text.splitlines()[0].startswith("name,sequence,status,frames")
    assert len(csv_text.splitlines()) == 5

    # Each results folder is what a serial 'jsr reconstruct' with the same settings writes.
    for name, start, options in (("a", 0, []), ("b", 5, ["--set", "seed=4"]),
                                 ("c", 10, ["--set", "objects.enabled=true", "--set", "ransac.min_matches=10"])):
        serial = tmp_path / f"serial_{name}"
        done = runner.invoke(app, ["reconstruct", str(sequences / "seq"), "--out", str(serial), "--save-masks",
                                   "--start", str(start), "--max-frames", str(FRAMES), "-q", *COARSE_MESH, *options])
        assert done.exit_code == 0, done.output
        assert digests(out / name) == digests(serial), name

    # A rerun skips what is complete with the same settings; a changed setting redoes that one.
    before = (out / "a" / "camera.tum").stat().st_mtime_ns
    manifest.write_text(f"sequence,name,start,max_frames,set\nseq,a,0,{FRAMES},\nseq,b,5,{FRAMES},seed=5\n")
    result = runner.invoke(app, ["batch", str(manifest), "--out", str(out), "--workers", "1", "--save-masks", "-q",
                                 "--json", *COARSE_MESH])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert {row["name"]: row["status"] for row in summary["sequences"]} == {"a": "skipped", "b": "complete"}
    assert (out / "a" / "camera.tum").stat().st_mtime_ns == before
    assert "seed: 5" in (out / "b" / "config.yaml").read_text()


def test_stopping_a_batch_interrupts_running_runs_and_says_so(sequences, tmp_path, monkeypatch):
    """Ctrl-C (here: a KeyboardInterrupt from the first finished row) tells the running task to
    stop; it writes the frames done; the summary says what was interrupted or not started. Run
    on an existing scheduler (--scheduler), an in-process one, so the stop check can be made
    immediate."""
    from distributed import LocalCluster

    import jsr.batch.task

    monkeypatch.setattr(jsr.batch.task, "STOP_CHECK_SECONDS", 0.0)
    entries = read_manifest_text(sequences, "sequence,name,max_frames\nmissing,first,\nseq,second,8\nseq,third,8\n")
    run_entry = jsr.batch.task._run_entry

    def first_fails_once_second_runs(entry, out_dir, settings, stop_event):
        """"first" fails at once, but only after "second" began its run (wrote its config):
        a worker thread slow to start (a cold first test) had "second" not started yet."""
        if entry.name == "first":
            began, deadline = out_dir / "second" / "config.yaml", time.monotonic() + 120.0
            while not began.exists() and time.monotonic() < deadline:
                time.sleep(0.01)
        return run_entry(entry, out_dir, settings, stop_event)

    monkeypatch.setattr(jsr.batch.task, "_run_entry", first_fails_once_second_runs)
    rows = []

    def stop_at_first(row):
        rows.append(row)
        if len(rows) == 1:
            raise KeyboardInterrupt

    # two threads: "second" starts beside "first", which fails at once and so stops the batch
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0") as cluster:
        with pytest.raises(KeyboardInterrupt):
            run_batch(entries, tmp_path / "out", BatchSettings(overrides=("output.mesh_voxel_size=0.05",)),
                      scheduler=cluster.scheduler_address,
                      on_result=stop_at_first)
    summary = json.loads((tmp_path / "out" / "batch_summary.json").read_text())
    assert summary["status"] == "interrupted"
    statuses = {row["name"]: row["status"] for row in summary["sequences"]}
    assert statuses["first"] == "failed"
    assert statuses["second"] == "interrupted"
    assert statuses["third"] in ("interrupted", "not started")
    assert "pending" not in statuses.values()
    for name, status in statuses.items():
        if status == "interrupted":  # its folder holds the frames done, and says so
            written = json.loads((tmp_path / "out" / name / "summary.json").read_text())
            assert written["status"] == "interrupted" and 1 <= written["frames_processed"] < 8


def read_manifest_text(folder: Path, text: str):
    (folder / "stop.csv").write_text(text)
    return read_manifest(folder / "stop.csv")


def test_batch_refuses_workers_with_a_scheduler_and_a_bad_manifest(tmp_path):
    (tmp_path / "m.csv").write_text("sequence\nx\n")
    result = runner.invoke(app, ["batch", str(tmp_path / "m.csv"), "--out", str(tmp_path / "o"), "--workers", "2",
                                 "--scheduler", "tcp://127.0.0.1:1"])
    assert result.exit_code == 2 and "not both" in result.output
    result = runner.invoke(app, ["batch", str(tmp_path / "nothing.csv"), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and result.output.startswith("error: manifest")
    result = runner.invoke(app, ["batch", str(tmp_path / "m.csv"), "--out", str(tmp_path / "o"), "--set", "nope=1"])
    assert result.exit_code == 2 and "nope" in result.output


def test_batch_table_keeps_long_names_within_80_columns():
    from rich.console import Console

    from jsr.summaries import batch_report

    rows = [{"name": "bonn_crowd_people_second_half", "status": "complete", "frames": 328, "fps": 0.5,
             "ate_rmse_cm": 12.3, "objects_true": 1, "objects_matched": 1, "object_t_rmse_cm_max": 1.5,
             "object_r_rmse_deg_max": 2.5}]
    console = Console(width=80, record=True, file=io.StringIO())
    for item in batch_report({"sequences": rows, "counts": {"complete": 1}}, Path("runs")):
        console.print(item)
    text = console.export_text()
    assert "…" not in text and max(len(line) for line in text.splitlines()) <= 80
    assert "bonn_crowd" in text and "half" in text  # folded onto two lines, whole
