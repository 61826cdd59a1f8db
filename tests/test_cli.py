"""The command line: every bad input gives one clear line and a non-zero exit code."""

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from jsr import __version__
from jsr.cli import app
from tests.helpers import colour_paths, depth_paths, write_tiny_tum

runner = CliRunner()


def run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    return result


def assert_one_line_error(result, fragment):
    assert result.exit_code != 0, result.output
    assert not isinstance(result.exception, Exception) or isinstance(result.exception, SystemExit), result.exception
    text = result.output.strip()
    assert "Traceback" not in text
    assert fragment in text, text
    assert text.startswith("error:"), text


def test_version():
    result = run("--version")
    assert result.exit_code == 0 and __version__ in result.output


@pytest.mark.parametrize("command", ["reconstruct", "synth", "evaluate", "plot", "export-object", "render", "batch"])
def test_help_has_examples(command):
    result = run(command, "--help")
    assert result.exit_code == 0
    assert "Example" in result.output


def test_reconstruct_writes_results(tmp_path, synth_sequence):
    out = tmp_path / "out"
    result = run("reconstruct", synth_sequence, "--out", out, "--set", "seed=5", "--max-frames", "6", "-q", "--render",
                 "--set", "output.mesh_voxel_size=0.03")
    assert result.exit_code == 0, result.output
    for name in ("config.yaml", "summary.json", "camera.tum", "landmarks.csv", "timings.csv",
                 "static/keyframes.tum", "static/landmarks.ply", "static/mesh.ply",
                 "plots/static_view_1.png", "plots/scene_frame_5.png"):
        assert (out / name).is_file(), name
    assert "seed: 5" in (out / "config.yaml").read_text()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "complete" and summary["frames_processed"] == 6


def test_progress_in_a_log_keeps_its_counts(tmp_path, synth_sequence):
    """Not on a terminal, the progress line's counts wrap within 80 columns rather than being cut."""
    result = run("reconstruct", synth_sequence, "--out", tmp_path / "out", "--max-frames", "4")
    assert result.exit_code == 0, result.output
    progress = result.output[:result.output.index("jsr reconstruct:")]
    assert "…" not in progress
    assert "4/4" in progress and "fps" in progress and " seen)" in progress


def make_bad_input(tmp_path, problem):
    seq = write_tiny_tum(tmp_path / "seq")
    args = ["reconstruct", seq, "--out", tmp_path / "out"]
    if problem == "missing folder":
        args[1] = tmp_path / "nowhere"
    elif problem == "no rgb.txt or pairs":
        (tmp_path / "empty").mkdir()
        args[1] = tmp_path / "empty"
    elif problem == "truncated image":
        data = colour_paths(seq)[0].read_bytes()
        colour_paths(seq)[0].write_bytes(data[:40])
    elif problem == "not an image":
        colour_paths(seq)[0].write_text("hello")
    elif problem == "depth size":
        cv2.imwrite(str(depth_paths(seq)[0]), np.full((10, 10), 5000, np.uint16))
    elif problem == "zero depth":
        for path in depth_paths(seq):
            cv2.imwrite(str(path), np.zeros((24, 32), np.uint16))
    elif problem == "config typo":
        args += ["--set", "ransac.min_matchs=3"]
    elif problem == "config file typo":
        (tmp_path / "c.yaml").write_text("ransac:\n  inlier_ratio: 0.3\n")
        args += ["--config", tmp_path / "c.yaml"]
    elif problem == "existing results":
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "summary.json").write_text("{}")
    elif problem == "wrong resolution":
        (seq / "camera.yaml").write_text("fx: 30\nfy: 30\ncx: 16\ncy: 12\nwidth: 640\nheight: 480\n")
    elif problem == "bad camera file":
        args += ["--camera", tmp_path / "nocam.yaml"]
    elif problem == "bad stride":
        args += ["--stride", "0"]
    elif problem == "binary rgb.txt":
        (seq / "rgb.txt").write_bytes(bytes(range(256)))
    elif problem == "binary config":
        (tmp_path / "c.yaml").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
        args += ["--config", tmp_path / "c.yaml"]
    elif problem == "negative seed":
        args += ["--set", "seed=-1"]
    elif problem == "bad init box":
        args += ["--init-box", "1,2,3"]
    elif problem == "init box off the image":
        args += ["--init-box", "1000,1000,2000,2000"]
    elif problem == "init box corners swapped":
        args += ["--init-box", "20,15,4,3"]
    elif problem == "init box negative":
        args += ["--init-box", "-5,-5,20,20"]
    elif problem == "init mask size":
        cv2.imwrite(str(tmp_path / "mask.png"), np.full((10, 10), 255, np.uint8))
        args += ["--init-object", tmp_path / "mask.png"]
    elif problem == "missing init mask":
        args += ["--init-object", tmp_path / "nomask.png"]
    elif problem == "short distortion":
        (seq / "camera.yaml").write_text("fx: 30\nfy: 30\ncx: 16\ncy: 12\nwidth: 32\nheight: 24\ndistortion: [1, 2]\n")
    elif problem == "fractional width":
        (seq / "camera.yaml").write_text("fx: 30\nfy: 30\ncx: 16\ncy: 12\nwidth: 32.5\nheight: 24\n")
    return args


BAD_INPUTS = {
    "missing folder": "does not exist",
    "no rgb.txt or pairs": "neither rgb.txt nor",
    "truncated image": "is truncated (no PNG end marker)",
    "not an image": "unreadable or truncated",
    "depth size": "register depth to colour",
    "zero depth": "no valid depth",
    "config typo": "unknown config key 'ransac.min_matchs'",
    "config file typo": "unknown config key 'ransac.inlier_ratio'",
    "existing results": "already holds results; pass --overwrite",
    "wrong resolution": "camera calibration is 640x480",
    "bad camera file": "does not exist",
    "bad stride": "--stride",
    "binary rgb.txt": "not a text file",
    "binary config": "not a text file",
    "negative seed": "'seed' must be a whole number >= 0",
    "fractional width": "width must be a whole number",
    "short distortion": "(k1 k2 p1 p2 [k3])",  # printed as written, not taken for rich markup
    "bad init box": "--init-box must be four integers",
    "init box off the image": "reaches outside the 32x24 image",
    "init box negative": "reaches outside the 32x24 image",
    "init box corners swapped": "top-left corner X0,Y0 first",
    "init mask size": "initial object mask",
    "missing init mask": "does not exist",
}


@pytest.mark.parametrize("problem", sorted(BAD_INPUTS))
def test_bad_input_gives_one_line(tmp_path, problem):
    result = run(*make_bad_input(tmp_path, problem))
    assert_one_line_error(result, BAD_INPUTS[problem])
    assert len(result.output.strip().splitlines()) <= 2  # one message (rich may wrap a long line once)


def test_overwrite_replaces_results(tmp_path):
    seq = write_tiny_tum(tmp_path / "seq")
    out = tmp_path / "out"
    run("reconstruct", seq, "--out", out, "-q")
    result = run("reconstruct", seq, "--out", out, "--overwrite", "--set", "seed=9", "-q")
    assert result.exit_code == 0, result.output
    assert "seed: 9" in (out / "config.yaml").read_text()


def test_json_summary_is_machine_readable(tmp_path):
    seq = write_tiny_tum(tmp_path / "seq")
    result = runner.invoke(app, ["reconstruct", str(seq), "--out", str(tmp_path / "o"), "--json", "-q"])
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1, result.stdout  # nothing else on stdout
    summary = json.loads(lines[0])
    assert summary["frames_processed"] == 4 and summary["status"] == "complete"


def test_export_object_and_plot_errors(tmp_path):
    (tmp_path / "res").mkdir()
    assert_one_line_error(run("export-object", tmp_path / "res", 1, "--out", tmp_path / "o.ply"), "has no object 1")
    assert_one_line_error(run("plot", tmp_path / "res"), "landmarks.csv does not exist")
    assert_one_line_error(run("evaluate", tmp_path / "res", tmp_path / "res"), "")


def test_export_object_input_errors(tmp_path):
    assert_one_line_error(run("export-object", tmp_path / "nowhere", 1, "--out", tmp_path / "o.ply"),
                          "results folder")
    (tmp_path / "res" / "objects" / "object_1").mkdir(parents=True)
    assert_one_line_error(run("export-object", tmp_path / "res", 1, "--out", tmp_path / "o.ply", "--timestamp", "1"),
                          "with --world")


def test_truncated_png_gives_one_line_and_no_libpng_message(tmp_path, capfd):
    """A PNG cut short is found before libpng decodes it, which would print its own line."""
    from jsr.cli import main

    seq = write_tiny_tum(tmp_path / "seq")
    data = depth_paths(seq)[1].read_bytes()
    depth_paths(seq)[1].write_bytes(data[: len(data) // 2])
    with pytest.raises(SystemExit) as stop:
        main(["reconstruct", str(seq), "--out", str(tmp_path / "out"), "-q"])
    assert stop.value.code == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "truncated" in err[0], err


def test_overlays_never_go_into_the_sequence_folder(tmp_path):
    seq = write_tiny_tum(tmp_path / "seq")
    before = colour_paths(seq)[0].read_bytes()
    assert_one_line_error(run("frames", seq, "--out", seq / "rgb", "--overwrite"), "inside the sequence folder")
    assert colour_paths(seq)[0].read_bytes() == before


def _results_with_object_mesh(root):
    """A results folder holding object 1's mesh.ply (one triangle), as jsr reconstruct writes it."""
    import open3d as o3d

    from jsr.io.writers import write_geometry_ply

    folder = root / "objects" / "object_1"
    folder.mkdir(parents=True)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.eye(3)), o3d.utility.Vector3iVector([[0, 1, 2]]))
    write_geometry_ply(folder / "mesh.ply", mesh)
    return folder / "mesh.ply"


def test_export_object_refuses_truncated_models_and_its_own_results(tmp_path):
    mesh = _results_with_object_mesh(tmp_path / "res")
    assert run("export-object", tmp_path / "res", 1, "--out", tmp_path / "ok.ply").exit_code == 0
    assert_one_line_error(run("export-object", tmp_path / "res", 1, "--out", mesh, "--overwrite"),
                          "is one of the models of the results folder")
    data = mesh.read_bytes()
    mesh.write_bytes(data[:-10])
    assert_one_line_error(run("export-object", tmp_path / "res", 1, "--out", tmp_path / "cut.ply"), "truncated")
    assert not (tmp_path / "cut.ply").exists()


def test_unwritable_output_paths_give_one_line(tmp_path):
    mesh = _results_with_object_mesh(tmp_path / "res")
    (tmp_path / "a_file").write_text("x")
    assert_one_line_error(run("export-object", tmp_path / "res", 1, "--out", tmp_path / "a_file" / "x.ply"),
                          "cannot read or write")
    (tmp_path / "folder.ply").mkdir()
    assert_one_line_error(run("export-object", tmp_path / "res", 1, "--out", tmp_path / "folder.ply", "--overwrite"),
                          "it is a folder")
    assert mesh.is_file()


@pytest.mark.parametrize("argv, fragment", [
    (["reconstruct", "seq"], "Missing option '--out'"),
    (["reconstrut"], "No such command 'reconstrut'"),
    (["reconstruct", "seq", "--out", "o", "--max-frames", "abc"], "'--max-frames'"),
    (["export-object", "res", "one", "--out", "o.ply"], "object_id"),
])
def test_usage_errors_give_one_line(argv, fragment, capsys):
    from jsr.cli import main

    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) <= 2 and lines[0].startswith("error:") and fragment in captured.err, captured.err
    assert captured.out == ""


def _stop_after(monkeypatch, frames: int, stop: BaseException):
    """Make the reconstructor raise ``stop`` on frame ``frames`` (0-based)."""
    from jsr.pipeline.reconstruct import Reconstructor

    process = Reconstructor.process

    def process_then_stop(self, frame):
        if len(self.reports) == frames:
            raise stop
        return process(self, frame)

    monkeypatch.setattr(Reconstructor, "process", process_then_stop)


@pytest.mark.parametrize("stop, code", [("interrupt", 130), ("terminate", 143)])
def test_stopped_run_still_prints_its_json_line(tmp_path, monkeypatch, stop, code):
    from jsr.cli import Terminated

    seq = write_tiny_tum(tmp_path / "seq")
    _stop_after(monkeypatch, 2, KeyboardInterrupt() if stop == "interrupt" else Terminated("terminated by SIGTERM"))
    result = runner.invoke(app, ["reconstruct", str(seq), "--out", str(tmp_path / "o"), "--json", "-q"])
    assert result.exit_code == code, result.output
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1, result.stdout
    summary = json.loads(lines[0])
    assert summary["status"] == "interrupted" and summary["frames_processed"] == 2


def test_internal_error_is_one_line(tmp_path, monkeypatch):
    seq = write_tiny_tum(tmp_path / "seq")
    _stop_after(monkeypatch, 1, RuntimeError("boom"))
    result = run("reconstruct", seq, "--out", tmp_path / "o", "-q")
    assert_one_line_error(result, "internal error (RuntimeError: boom)")
    assert result.exit_code == 1
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["status"] == "failed"


def test_synth_reports_bad_options_before_any_progress(tmp_path):
    result = run("synth", tmp_path / "s", "--motion", "wobble")
    assert_one_line_error(result, "wobble")
    assert len(result.output.strip().splitlines()) == 1, result.output
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    result = run("synth", tmp_path / "full", "--frames", "3")
    assert_one_line_error(result, "is not empty")
    assert len(result.output.strip().splitlines()) == 1, result.output


def test_frames_refuses_a_full_folder(tmp_path):
    seq = write_tiny_tum(tmp_path / "seq")
    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "old.png").write_bytes(b"x")
    assert_one_line_error(run("frames", seq, "--out", tmp_path / "f", "-q"), "pass --overwrite")
    result = run("frames", seq, "--out", tmp_path / "f", "--overwrite", "-q", "--max-frames", "1")
    assert result.exit_code == 0, result.output
