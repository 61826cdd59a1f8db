"""The ``jsr`` command line: the only place that prints, and the only place that exits.

Every command is a thin shell around a library function (named in its docstring) so
that anything done here can also be scripted from Python.
"""

from __future__ import annotations

import functools
import importlib
import json
import logging
import signal
import sys
import time
from pathlib import Path
from typing import Callable, List, Optional

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Column, Table

from jsr import __version__
from jsr.errors import JsrError

app = typer.Typer(
    name="jsr",
    help="Joint reconstruction of a static scene and rigidly moving objects from RGB-D sequences.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)
console = Console(stderr=True, highlight=False)
logger = logging.getLogger("jsr")

EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports Ctrl-C
EXIT_TERMINATED = 143  # 128 + SIGTERM
EXIT_INTERNAL_ERROR = 1


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a batch scheduler): handled as Ctrl-C is, so that the
    results of the frames done are written."""


def _raise_terminated(_signum, _frame) -> None:
    raise Terminated("terminated by SIGTERM")


def _configure_logging(verbose: int, quiet: bool) -> None:
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    root = logging.getLogger("jsr")
    root.handlers.clear()
    handler = RichHandler(console=console, show_time=False, show_path=False, markup=False)
    handler.setFormatter(logging.Formatter("%(message)s"))
    root.addHandler(handler)
    root.setLevel(level)
    root.propagate = False


def _fail(message: str, code: int = 2) -> None:
    # escaped: a message quoting a list or a path with brackets is not rich markup
    console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)
    raise typer.Exit(code)


def _user_errors(command: Callable) -> Callable:
    """Turn a :class:`JsrError` into one line on stderr and a non-zero exit code."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except JsrError as error:
            _fail(str(error), error.exit_code)
        except KeyboardInterrupt as interrupt:
            console.print("[yellow]interrupted[/]")
            raise typer.Exit(_interrupt_exit_code(interrupt))
        except (typer.Exit, typer.Abort):
            raise
        except OSError as error:  # a path that cannot be read or written (a folder, no permission, ...)
            logger.debug("traceback of the file error", exc_info=True)
            where = f" {error.filename}" if error.filename else ""
            _fail(f"cannot read or write{where}: {error.strerror or error}; check the path and its permissions")
        except Exception as error:  # a bug: one line; the traceback with -vv
            logger.debug("traceback of the internal error", exc_info=True)
            _fail(f"internal error ({type(error).__name__}: {error}); this is a bug in jsr: please report it with "
                  "the command line (-vv shows the traceback)", EXIT_INTERNAL_ERROR)

    return wrapper


def _interrupt_exit_code(interrupt: KeyboardInterrupt) -> int:
    return EXIT_TERMINATED if isinstance(interrupt, Terminated) else EXIT_INTERRUPTED


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"jsr {__version__}")
        raise typer.Exit()


@app.callback()
def _main_options(
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """Joint reconstruction of a static scene and rigidly moving objects from RGB-D sequences."""


def _progress(quiet: bool) -> Progress:
    """Rich progress on stderr; the rate and map counts come last and wrap rather than being cut
    in a narrow window. Not on a terminal (a batch job's log) rich draws only the final state:
    the bar and the times are left out there."""
    counts = TextColumn("{task.fields[rate]}", table_column=Column(no_wrap=False, overflow="fold"))
    if console.is_terminal:
        columns = [TextColumn("[bold]{task.description}"), BarColumn(bar_width=20), MofNCompleteColumn(),
                   TimeElapsedColumn(), TimeRemainingColumn(), counts]
    else:
        columns = [TextColumn("{task.description}"), MofNCompleteColumn(), counts]
    return Progress(*columns, console=console, disable=quiet, transient=False)


def _print_json(data: dict) -> None:
    """Machine-readable output goes to stdout, alone on one line."""
    from jsr.io.writers import to_json_text

    sys.stdout.write(json.dumps(json.loads(to_json_text(data))) + "\n")
    sys.stdout.flush()


def _open_sequence(sequence: Path, config, camera, preset, start, max_frames, stride):
    """Open a sequence with the input settings of ``config`` (shared by the commands)."""
    from jsr.io.dataset import open_sequence

    return open_sequence(
        sequence,
        camera_file=camera,
        preset=preset,
        max_time_difference=config.input.max_time_difference,
        start=start,
        max_frames=max_frames,
        stride=stride,
        min_depth=config.input.min_depth,
        max_depth=config.input.max_depth,
    )


def _fps_reporter(progress: Progress, task, started: float) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that shows frames per second."""

    def report(done: int, total: int) -> None:
        elapsed = time.perf_counter() - started
        progress.update(task, completed=done, total=total, rate=f"{done / max(elapsed, 1e-9):.1f} fps")

    return report


SEQUENCE_HELP = "Sequence folder: TUM RGB-D layout (rgb.txt, depth.txt) or a set of colour/depth image pairs."


@app.command(
    epilog="Examples:\n\n  jsr reconstruct sample_data --out results/\n\n"
    "  jsr reconstruct seq/ --out runs/a --set ransac.min_inlier_ratio=0.5 --max-frames 200 -q --json\n\n"
    "  jsr reconstruct scene3/ --out runs/s3 --init-box 200,150,320,260 --save-masks"
)
@_user_errors
def reconstruct(
    sequence: Path = typer.Argument(..., help=SEQUENCE_HELP, show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Results folder (created; must be new or empty)."),
    config_file: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config overriding defaults."),
    overrides: List[str] = typer.Option([], "--set", help="Override one key: section.key=value (repeatable)."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="camera.yaml to use instead of SEQ/camera.yaml."),
    preset: Optional[str] = typer.Option(
        None, "--preset", help="Named intrinsics: tum-fr1, tum-fr2, tum-fr3, icl-nuim, bonn, primesense."
    ),
    start: int = typer.Option(0, "--start", help="First frame to use (index into the associated frames)."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="Use at most this many frames."),
    stride: int = typer.Option(1, "--stride", help="Use every STRIDE-th frame."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the results already in --out."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar or table; errors only."),
    json_summary: bool = typer.Option(False, "--json", help="Print a one-line JSON summary on stdout."),
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log output (-v info, -vv debug)."),
    save_masks: bool = typer.Option(False, "--save-masks", help="Write masks/<frame>.png: 0 static, K object K."),
    init_object: Optional[Path] = typer.Option(
        None, "--init-object", help="PNG mask (non-zero = object) on the first frame: start object 1 there."),
    init_box: Optional[str] = typer.Option(
        None, "--init-box", help="Pixel box X0,Y0,X1,Y1 on the first frame: start object 1 there."),
) -> None:
    """Reconstruct a sequence: camera trajectory, static map, and a map and trajectory for
    every moving object, with their meshes."""
    from jsr.config import load_config
    from jsr.io.dataset import check_first_frame
    from jsr.io.run_folder import prepare_output_folder

    _configure_logging(verbose, quiet)
    config = load_config(config_file, overrides)
    data = _open_sequence(sequence, config, camera, preset, start, max_frames, stride)
    first = check_first_frame(data)
    init_mask = _initial_object_mask(init_object, init_box, first.depth.shape)
    out_dir = prepare_output_folder(out, overwrite)

    from jsr.pipeline.run import run_reconstruction

    started = time.perf_counter()
    with _progress(quiet) as progress:
        task = progress.add_task("reconstruct", total=len(data), rate="")

        def on_frame(report) -> None:
            done = report.frame_index + 1
            elapsed = time.perf_counter() - started
            maps = report.maps
            static = maps.get("static")
            objects = sum(1 for name in maps if name != "static")
            tracked = len(report.objects_tracked)
            state = "" if report.tracked else " [yellow]lost[/]"
            progress.update(
                task,
                completed=done,
                rate=f"{done / max(elapsed, 1e-9):.1f} fps | static kf {static.keyframes if static else 0} "
                f"pts {static.point_landmarks if static else 0} | objects {objects} ({tracked} seen){state}",
            )

        stopped: BaseException | None = None
        try:
            summary = run_reconstruction(data, config, out_dir, on_frame=on_frame, save_masks=save_masks,
                                         init_object_mask=init_mask)
        except BaseException as error:  # reported below, once the progress bar has drawn its last line
            stopped = error
    if stopped is not None:
        if json_summary:  # a batch job still gets its line, with "status" interrupted or failed
            _print_summary_file(out_dir / "summary.json")
        if isinstance(stopped, KeyboardInterrupt):
            console.print(f"[yellow]interrupted[/]: results of the frames done are in {escape(str(out_dir))}")
            raise typer.Exit(_interrupt_exit_code(stopped)) from None
        raise stopped
    if json_summary:
        _print_json(summary)
    if not quiet:
        _print_run_summary(summary, out_dir)


def _print_summary_file(path: Path) -> None:
    """The JSON line of a run that stopped early, from the ``summary.json`` it left."""
    try:
        _print_json(json.loads(path.read_text()))
    except (OSError, ValueError):
        logger.debug("no readable %s to print", path)


def _initial_object_mask(mask_file: Optional[Path], box: Optional[str], shape: tuple[int, int]):
    """The ``(H, W)`` bool mask of ``--init-object`` or ``--init-box`` (None without either)."""
    from jsr.errors import InputError

    if mask_file is not None and box is not None:
        raise InputError("give --init-object or --init-box, not both")
    height, width = shape
    if box is not None:
        try:
            x0, y0, x1, y1 = (int(v) for v in box.split(","))
        except ValueError:
            raise InputError(f"--init-box must be four integers X0,Y0,X1,Y1, got '{box}'") from None
        if x1 <= x0 or y1 <= y0:
            raise InputError(f"--init-box {box}: give the top-left corner X0,Y0 first, then the bottom-right X1,Y1")
        if min(x0, y0) < 0 or x1 > width or y1 > height:
            raise InputError(f"--init-box {box} reaches outside the {width}x{height} image: pixel coordinates go "
                             f"from 0,0 to {width},{height}")
        if x1 - x0 < 2 or y1 - y0 < 2:
            raise InputError(f"--init-box {box} is less than 2 pixels wide or high")
        import numpy as np

        mask = np.zeros(shape, dtype=bool)
        mask[y0:y1, x0:x1] = True
        return mask
    if mask_file is None:
        return None
    import cv2
    import numpy as np

    if not Path(mask_file).is_file():
        raise InputError(f"initial object mask {mask_file} does not exist")
    image = cv2.imread(str(mask_file), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"initial object mask {mask_file} is not a readable image")
    if image.ndim == 3:
        image = image.max(axis=2)
    if image.shape != shape:
        raise InputError(f"initial object mask {mask_file} is {image.shape[1]}x{image.shape[0]} but the frames are "
                         f"{width}x{height}")
    if not np.any(image > 0):
        raise InputError(f"initial object mask {mask_file} has no non-zero pixel")
    return image > 0


def _print_run_summary(summary: dict, out_dir: Path) -> None:
    table = Table(title=f"jsr reconstruct: {summary['frames_processed']} frames, {summary['fps']:.2f} fps")
    for column in ("map", "keyframes", "point landmarks", "plane landmarks"):
        table.add_column(column, justify="right" if column != "map" else "left")
    for name, counts in summary["maps"].items():
        table.add_row(name, str(counts["keyframes"]), str(counts["point_landmarks"]), str(counts["plane_landmarks"]))
    console.print(table)
    for item in summary.get("objects", []):
        console.print(f"object {item['id']}: detected at frame {item['created_at_frame']}, "
                      f"tracked in {item['frames_tracked']} frames")
    console.print(
        f"tracked {summary['frames_tracked']} of {summary['frames_processed']} frames "
        f"({summary['frames_lost']} lost, {summary['relocalisations']} relocalisations); results in {out_dir}"
    )


@app.command(
    epilog="Examples:\n\n  jsr synth out/seq --frames 60 --objects 1 --motion jump\n\n"
    "  jsr synth out/two --objects 2 --motion smooth --simultaneous --width 320 --height 240 --seed 3\n\n"
    "  jsr synth out/kitchen --background ../shared/data/redkitchen300 --start 60 --frames 120 --seed 1"
)
@_user_errors
def synth(
    out: Path = typer.Argument(..., help="Folder to write the sequence into (new or empty)."),
    frames: int = typer.Option(60, "--frames", help="Number of frames."),
    objects: int = typer.Option(1, "--objects", help="Number of rigid moving objects (0: static scene)."),
    motion: str = typer.Option("jump", "--motion", help="Object motion: jump, smooth or static."),
    simultaneous: bool = typer.Option(False, "--simultaneous", help="Move all objects in the same frames."),
    background: Optional[Path] = typer.Option(
        None, "--background", help="A real TUM RGB-D sequence with groundtruth.txt and camera.yaml: composite the "
        "objects into its frames (its camera, size and timestamps) instead of rendering a room.",
    ),
    start: int = typer.Option(0, "--start", help="With --background: its first frame to use."),
    period: Optional[int] = typer.Option(
        None, "--period", help="With --background: frames between two motions (default 15)."
    ),
    width: Optional[int] = typer.Option(None, "--width", help="Image width in pixels (default 640)."),
    height: Optional[int] = typer.Option(None, "--height", help="Image height in pixels (default 480)."),
    noise: bool = typer.Option(True, "--noise/--no-noise", help="Kinect-like depth noise sigma_Z = 1.425e-3 Z^2."),
    dropout: float = typer.Option(0.02, "--dropout", help="Fraction of depth pixels dropped at random."),
    image_format: Optional[str] = typer.Option(
        None, "--format", help="Colour image format: png or jpg (default png; with --background, the background's)."
    ),
    seed: int = typer.Option(0, "--seed", help="Random seed; the same seed gives the same files."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a sequence already in OUT."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    json_summary: bool = typer.Option(False, "--json", help="Print a one-line JSON summary on stdout."),
) -> None:
    """Write a synthetic RGB-D sequence with exact ground truth (camera, objects, labels), or
    composite rendered objects into a real sequence (--background)."""
    from jsr.synth.options import COMPOSITE_PERIOD, CompositeOptions, SynthOptions, validate_options
    from jsr.synth.write import check_output_folder, generate_sequence

    _configure_logging(0, quiet)
    if background is not None:
        if width is not None or height is not None:
            _fail("--width and --height cannot be used with --background: a composite has the background's size")
        options = CompositeOptions(
            background=str(background),
            frames=frames,
            start=start,
            objects=objects,
            motion=motion,
            simultaneous=simultaneous,
            depth_noise=noise,
            dropout=dropout,
            seed=seed,
            image_format=image_format,
            period=COMPOSITE_PERIOD if period is None else period,
        )
        _synth_composite(out, options, overwrite, quiet, json_summary)
        return
    for name, given in (("--start", start != 0), ("--period", period is not None)):
        if given:
            _fail(f"{name} needs --background (it selects the frames of a real sequence)")
    options = SynthOptions(
        frames=frames,
        objects=objects,
        motion=motion,
        simultaneous=simultaneous,
        width=640 if width is None else width,
        height=480 if height is None else height,
        depth_noise=noise,
        dropout=dropout,
        seed=seed,
        image_format="png" if image_format is None else image_format,
    )
    validate_options(options)  # bad options and a full folder are reported before the progress bar starts
    check_output_folder(out, overwrite)
    started = time.perf_counter()
    with _progress(quiet) as progress:
        task = progress.add_task("synth", total=frames, rate="")
        report = _fps_reporter(progress, task, started)

        summary = generate_sequence(out, options, overwrite=overwrite, progress=report)
    if json_summary:
        _print_json(summary)
    if not quiet:
        console.print(f"wrote {frames} frames with {objects} object(s) to {out}")


def _synth_composite(out: Path, options, overwrite: bool, quiet: bool, json_summary: bool) -> None:
    """``jsr synth OUT --background SEQ``: :func:`jsr.synth.composite.generate_composite`."""
    from jsr.synth.background import open_background
    from jsr.synth.composite import check_composite_output, generate_composite
    from jsr.synth.options import validate_composite_options

    options = validate_composite_options(options)
    # A bad background or a full folder are reported before the progress bar starts.
    open_background(options.background, options.start, options.frames)
    check_composite_output(out, options, overwrite)
    started = time.perf_counter()
    with _progress(quiet) as progress:
        task = progress.add_task("composite", total=options.frames, rate="")
        report = _fps_reporter(progress, task, started)
        summary = generate_composite(out, options, overwrite=overwrite, progress=report)
    if json_summary:
        _print_json(summary)
    if not quiet:
        in_view = ", ".join(str(count) for count in summary["frames_in_view"]) or "-"
        console.print(
            f"wrote {options.frames} frames of {options.background} with {options.objects} object(s) on a surface of "
            f"{summary['surface_area_m2']:.2f} m2 (frames in view per object: {in_view}) to {out}"
        )


@app.command(epilog="Examples:\n\n  jsr frames sample_data --out overlays/ --stride 5\n\n"
             "  jsr frames seq/ --out overlays/ --start 100 --max-frames 10")
@_user_errors
def frames(
    sequence: Path = typer.Argument(..., help=SEQUENCE_HELP, show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for one overlay PNG per frame."),
    config_file: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config overriding defaults."),
    overrides: List[str] = typer.Option([], "--set", help="Override one key: section.key=value (repeatable)."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="camera.yaml to use instead of SEQ/camera.yaml."),
    preset: Optional[str] = typer.Option(None, "--preset", help="Named intrinsics (see 'reconstruct --help')."),
    start: int = typer.Option(0, "--start", help="First frame to use."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="Use at most this many frames."),
    stride: int = typer.Option(1, "--stride", help="Use every STRIDE-th frame."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Write into a folder that already holds files."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Draw what the front-end sees: keypoints (green 3D, red 2D), planes and segments per frame."""
    from jsr.config import load_config
    from jsr.pipeline.overlays import write_frame_overlays

    _configure_logging(0, quiet)
    config = load_config(config_file, overrides)
    data = _open_sequence(sequence, config, camera, preset, start, max_frames, stride)
    if out.exists() and not out.is_dir():
        _fail(f"--out {out} is a file; give a folder")
    if out.resolve().is_relative_to(sequence.resolve()):
        _fail(f"--out {out} is inside the sequence folder {sequence}, whose images overlays could replace; "
              "choose a folder outside it")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        _fail(f"--out {out} is not empty; pass --overwrite (overlays of the same frames are replaced) "
              "or choose another folder")
    started = time.perf_counter()
    with _progress(quiet) as progress:
        task = progress.add_task("frames", total=len(data), rate="")
        report = _fps_reporter(progress, task, started)

        written = write_frame_overlays(data, config, out, progress=report)
    if not quiet:
        console.print(f"wrote {len(written)} overlays to {out}")


@app.command(epilog="Example:\n\n  jsr evaluate results/ sample_data/")
@_user_errors
def evaluate(
    results: Path = typer.Argument(..., help="Results folder of 'jsr reconstruct'."),
    sequence: Path = typer.Argument(..., help="The sequence folder, with groundtruth.txt."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No tables; still writes metrics.json."),
    json_summary: bool = typer.Option(False, "--json", help="Print the metrics as one line of JSON on stdout."),
) -> None:
    """Compare a results folder with ground truth; writes RESULTS/metrics.json."""
    from jsr.evaluate.run import evaluate_run, write_metrics

    _configure_logging(0, quiet)
    metrics = evaluate_run(results, sequence)
    path = write_metrics(results, metrics)
    if json_summary:
        _print_json(metrics)
    if not quiet:
        _print_metrics(metrics)
        console.print(f"metrics written to {path}")


def _print_metrics(metrics: dict) -> None:
    camera = metrics.get("camera") or {}
    table = Table(title="Camera")
    table.add_column("metric")
    table.add_column("value", justify="right")
    ate, rpe = camera.get("ate") or {}, camera.get("rpe") or {}
    for label, value, unit in (
        ("ATE RMSE", ate.get("rmse"), "cm"),
        ("ATE median", ate.get("median"), "cm"),
        ("ATE max", ate.get("max"), "cm"),
        ("RPE translation RMSE", rpe.get("translation_rmse"), "cm"),
        ("RPE rotation RMSE", rpe.get("rotation_rmse"), "deg"),
    ):
        if value is not None:
            shown = value * 100.0 if unit == "cm" else value
            table.add_row(label, f"{shown:.3f} {unit}")
    for key in ("frames_associated", "gt_frames_without_estimate"):
        if key in camera:
            table.add_row(key.replace("_", " "), str(camera[key]))
    console.print(table)
    objects = metrics.get("objects") or {}
    matches = objects.get("matches") or []
    if matches:
        table = Table(title="Objects")
        for column in ("estimated", "true", "frames", "t RMSE cm", "t median cm", "R RMSE deg", "tracked share",
                       "further maps", "share, all maps"):
            table.add_column(column, justify="right")
        for match in matches:
            table.add_row(
                str(match.get("estimated_id")),
                str(match.get("true_id")),
                str(match.get("frames")),
                f"{match.get('translation_rmse_cm', float('nan')):.2f}",
                f"{match.get('translation_median_cm', float('nan')):.2f}",
                f"{match.get('rotation_rmse_deg', float('nan')):.2f}",
                f"{match.get('tracked_share', float('nan')):.2f}",
                ", ".join(str(k) for k in match.get("further_maps", [])) or "-",
                f"{match.get('tracked_share_all_maps', float('nan')):.2f}",
            )
        console.print(table)
    masks = metrics.get("masks")
    if masks:
        console.print(
            f"masks: precision {masks.get('precision', float('nan')):.3f}, "
            f"recall {masks.get('recall', float('nan')):.3f} over {masks.get('frames', 0)} frames"
        )


@app.command(epilog="Example:\n\n  jsr plot results/ --groundtruth sample_data/groundtruth.txt")
@_user_errors
def plot(
    results: Path = typer.Argument(..., help="Results folder of 'jsr reconstruct'."),
    groundtruth: Optional[Path] = typer.Option(None, "--groundtruth", help="TUM ground truth to draw beside."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for the PNGs (default RESULTS/plots)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing."),
) -> None:
    """Draw the paper's Figure 7 (keyframes and landmarks per map over frames) and the trajectory."""
    from jsr.export.plots import plot_landmark_counts, plot_trajectory

    _configure_logging(0, quiet)
    out_dir = out or Path(results) / "plots"
    if out_dir.exists() and not out_dir.is_dir():
        _fail(f"--out {out_dir} is a file; give a folder")
    written = [plot_landmark_counts(Path(results) / "landmarks.csv", out_dir / "landmarks.png")]
    if (Path(results) / "camera.tum").is_file():
        written.append(plot_trajectory(Path(results) / "camera.tum", out_dir / "trajectory.png", groundtruth))
    if not quiet:
        for path in written:
            console.print(f"wrote {path}")


@app.command("export-object", epilog="Examples:\n\n  jsr export-object results/ 1 --out box.ply\n\n"
             "  jsr export-object results/ 1 --out box_world.ply --kind cloud --world --timestamp 1000.5")
@_user_errors
def export_object_command(
    results: Path = typer.Argument(..., help="Results folder of 'jsr reconstruct'."),
    object_id: int = typer.Argument(..., help="Object number K (objects/object_K)."),
    out: Path = typer.Option(..., "--out", "-o", help="PLY file to write."),
    kind: str = typer.Option("mesh", "--kind", help="mesh, cloud or landmarks."),
    world: bool = typer.Option(False, "--world", help="Place the model in the world frame (first camera)."),
    timestamp: Optional[float] = typer.Option(
        None, "--timestamp", help="With --world: the pose of the tracked frame nearest this time (default: the "
        "first frame the object was tracked in)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUT if it exists."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing."),
) -> None:
    """Export the model of one reconstructed object as PLY, in its own frame or in the world."""
    from jsr.export.objects import export_object

    _configure_logging(0, quiet)
    written = export_object(results, object_id, out, kind=kind, in_world=world, timestamp=timestamp, overwrite=overwrite)
    if not quiet:
        console.print(f"wrote {written['kind']} of object {object_id} ({written['frame']} frame) to {out}")


def _usage_error_types() -> tuple[type[Exception], ...]:
    """Click's UsageError (Typer may bundle its own copy of Click)."""
    found = []
    for module in ("typer._click.exceptions", "click.exceptions"):
        try:
            found.append(importlib.import_module(module).UsageError)
        except (ImportError, AttributeError):
            continue
    return tuple(found)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point. Usage errors (an unknown option, a missing argument, a
    value of the wrong type) are one line on stderr and exit code 2, as every other bad input;
    SIGTERM is handled as Ctrl-C (the results of the frames done are written)."""
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _raise_terminated)
    usage_errors = _usage_error_types()
    try:
        code = app(args=argv, prog_name="jsr", standalone_mode=False)
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # done: a late Ctrl-C must not turn the exit into a traceback
    except usage_errors as error:
        if type(error).__name__ == "NoArgsIsHelpError":  # bare 'jsr': the help was printed
            sys.exit(2)
        command = error.ctx.command_path if getattr(error, "ctx", None) is not None else "jsr"
        console.print(f"[bold red]error:[/] {escape(error.format_message())} (see '{command} --help')", soft_wrap=True)
        sys.exit(2)
    except (KeyboardInterrupt, typer.Abort) as interrupt:  # before a command took over
        sys.exit(_interrupt_exit_code(interrupt) if isinstance(interrupt, KeyboardInterrupt) else EXIT_INTERRUPTED)
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":
    main()
