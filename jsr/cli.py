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
from rich.table import Column

from jsr import __version__
from jsr.errors import JsrError
from jsr.summaries import (batch_counts, batch_line, batch_report, metrics_report, rendered_report,
                           run_summary)

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
EXIT_SOME_FAILED = 3  # jsr batch: the batch ran, and some of its sequences failed


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
    from jsr.pipeline.run import open_configured_sequence

    return open_configured_sequence(sequence, config, camera, preset, start, max_frames, stride)


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
    render: bool = typer.Option(False, "--render", help="At the end, write PNG previews to OUT/plots (as 'jsr render')."),
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

    from jsr.pipeline.run import run_reconstruction, single_threaded_blas

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
            with single_threaded_blas():  # the same files as in a jsr batch worker, on any core count
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
    rendered = None
    if render:
        from jsr.export.render import render_results

        with console.status("rendering previews", spinner="dots") if not quiet else _no_status():
            rendered = render_results(out_dir)
    if json_summary:
        _print_json(summary if rendered is None else {**summary, "render": rendered})
    if not quiet:
        _show(run_summary(summary, out_dir))
        if rendered is not None:
            _show(rendered_report(rendered))


def _show(renderables: list) -> None:
    for item in renderables:
        console.print(item)


def _no_status():
    from contextlib import nullcontext

    return nullcontext()


def _read_json(path: Path) -> dict:
    """A JSON file the command wrote, or {} when it is not there or not readable."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


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
        _show(metrics_report(metrics))
        console.print(f"metrics written to {path}")


@app.command(epilog="Examples:\n\n  jsr plot results/\n\n  jsr plot results/ --sequence sample_data/\n\n"
             "  jsr plot results/ --groundtruth other/groundtruth.txt --out figures/")
@_user_errors
def plot(
    results: Path = typer.Argument(..., help="Results folder of 'jsr reconstruct'."),
    sequence: Optional[Path] = typer.Option(
        None, "--sequence", help="Sequence folder with ground truth (default: the one the run read, if there)."),
    groundtruth: Optional[Path] = typer.Option(None, "--groundtruth", help="TUM camera ground truth to draw beside."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for the PNGs (default RESULTS/plots)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing."),
) -> None:
    """Draw the paper's Figure 7 (keyframes and landmarks per map over frames) and the camera
    and object trajectories, with the ground truth aligned as 'jsr evaluate' aligns it."""
    from jsr.errors import InputError
    from jsr.export.plots import plot_results

    _configure_logging(0, quiet)
    out_dir = out or Path(results) / "plots"
    if out_dir.exists() and not out_dir.is_dir():
        _fail(f"--out {out_dir} is a file; give a folder")
    if sequence is not None and not sequence.is_dir():
        raise InputError(f"sequence folder {sequence} does not exist")
    if groundtruth is not None and not groundtruth.is_file():
        raise InputError(f"ground truth {groundtruth} does not exist")
    written = plot_results(results, out_dir, sequence, groundtruth)
    if not quiet:
        for path in written:
            console.print(f"wrote {path}")


@app.command(epilog="Examples:\n\n  jsr render results/\n\n"
             "  jsr render results/ --frame 20 --views 4 --width 1024 --out previews/")
@_user_errors
def render(
    results: Path = typer.Argument(..., help="Results folder of 'jsr reconstruct' (a complete run, with meshes)."),
    frame: Optional[int] = typer.Option(
        None, "--frame", help="Frame whose object poses the scene view shows (default: the last processed)."),
    views: int = typer.Option(3, "--views", help="Number of static-map views, spread along the camera path."),
    width: int = typer.Option(800, "--width", help="Image width in pixels (height: the sequence's aspect ratio)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for the PNGs (default RESULTS/plots)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing but errors."),
    json_summary: bool = typer.Option(False, "--json", help="Print what was written as one line of JSON."),
) -> None:
    """Render PNG previews on the CPU (no display needed): the static mesh from viewpoints along
    the camera path, the scene with every object placed at its pose in a frame, each in its own
    tint (the paper's Figure 6 A), and each object model alone (Figure 6 D)."""
    from jsr.export.render import render_results

    _configure_logging(0, quiet)
    if out is not None and out.exists() and not out.is_dir():
        _fail(f"--out {out} is a file; give a folder")
    with console.status("rendering previews", spinner="dots") if not quiet else _no_status():
        rendered = render_results(results, out, frame=frame, views=views, width=width)
    if json_summary:
        _print_json(rendered)
    if not quiet:
        _show(rendered_report(rendered))


@app.command(epilog="Examples:\n\n  jsr batch manifest.csv --out runs/\n\n"
             "  jsr batch manifest.yaml --out runs/ --workers 2 --save-masks --render\n\n"
             "  jsr batch manifest.csv --out runs/ --scheduler tcp://scheduler-host:8786 -q --json\n\n"
             "manifest.csv:\n\n  sequence,name,preset,start,max_frames,set\n\n"
             "  data/kitchen,,,0,300,\n\n  data/office,office_fast,bonn,,,ransac.min_matches=12;seed=1")
@_user_errors
def batch(
    manifest: Path = typer.Argument(..., help="CSV (header: sequence[,name,preset,start,max_frames,set]) or YAML."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for one results folder per sequence and the summary."),
    workers: Optional[int] = typer.Option(
        None, "--workers", help="Worker processes of the local cluster (default: one per two cores)."),
    scheduler: Optional[str] = typer.Option(
        None, "--scheduler", help="Address of a running Dask scheduler to use instead (tcp://host:8786)."),
    config_file: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config for every sequence."),
    overrides: List[str] = typer.Option([], "--set", help="Override for every sequence: section.key=value."),
    save_masks: bool = typer.Option(False, "--save-masks", help="Write masks/ in each results folder."),
    render: bool = typer.Option(False, "--render", help="Write PNG previews in each results folder."),
    force: bool = typer.Option(False, "--force", help="Redo sequences whose results are complete."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress or lines per sequence; errors only."),
    json_summary: bool = typer.Option(False, "--json", help="Print the batch summary as one line of JSON."),
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log output (-v info, -vv debug)."),
) -> None:
    """Reconstruct the sequences of a manifest, each as one task on Dask (a local cluster, or
    an existing scheduler). Each gets the results folder 'jsr reconstruct' writes, evaluated
    when it has ground truth; OUT/batch_summary.csv and .json are written as tasks finish. A
    rerun skips sequences already complete with the same settings; a failing sequence is
    recorded and the others go on. Exit code 3 when some sequence failed."""
    from jsr.batch.manifest import read_manifest
    from jsr.batch.run import run_batch
    from jsr.batch.task import BatchSettings
    from jsr.config import load_config

    _configure_logging(verbose, quiet)
    logging.getLogger("distributed").setLevel(logging.ERROR)  # its worker chatter is not the user's business
    entries = read_manifest(manifest)
    load_config(config_file, overrides)  # a typo in the options shared by all is reported before anything runs
    settings = BatchSettings(config_file=config_file, overrides=tuple(overrides), save_masks=save_masks,
                             render=render, force=force)
    started = time.perf_counter()
    with _progress(quiet) as progress:
        task = progress.add_task("batch", total=len(entries), rate="")

        def on_result(row: dict) -> None:
            if not quiet:
                progress.console.print(batch_line(row), soft_wrap=True)
                notes = [row[key] for key in ("render_error", "evaluation_error") if row.get(key)]
                for warning in [*(row.get("warnings") or []), *notes]:
                    progress.console.print(f"  [yellow]warning[/] {escape(warning)}", soft_wrap=True)
            if row["status"] not in ("interrupted", "not started"):
                progress.advance(task)
            done = int(progress.tasks[0].completed)
            progress.update(task, rate=f"{done / max(time.perf_counter() - started, 1e-9) * 3600:.1f} sequences/h")

        stopped: KeyboardInterrupt | None = None
        try:
            summary = run_batch(entries, out, settings, workers=workers, scheduler=scheduler, on_result=on_result)
        except KeyboardInterrupt as interrupt:
            stopped = interrupt
    if stopped is not None:
        if json_summary:
            _print_summary_file(out / "batch_summary.json")
        counts = batch_counts(_read_json(out / "batch_summary.json"))
        console.print(f"[yellow]interrupted[/]: {counts}; summary in {escape(str(out / 'batch_summary.csv'))}")
        raise typer.Exit(_interrupt_exit_code(stopped))
    if json_summary:
        _print_json(summary)
    if not quiet:
        _show(batch_report(summary, out))
    if summary["counts"].get("failed"):
        raise typer.Exit(EXIT_SOME_FAILED)


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
