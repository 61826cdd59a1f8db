"""What the CLI shows at the end of a command, as rich renderables (tables and marked-up
lines). Nothing here prints: :mod:`jsr.cli` prints them, and a script can as well."""

from __future__ import annotations

from pathlib import Path

from rich.markup import escape
from rich.table import Table


def figure(value) -> str:
    """A figure with two decimals, '-' when undefined (None in the metrics)."""
    return "-" if value is None else f"{value:.2f}"


def run_summary(summary: dict, out_dir: Path) -> list:
    """A reconstruction's ``summary.json``: the maps table, one line per object, the tracking line."""
    table = Table(title=f"jsr reconstruct: {summary['frames_processed']} frames, {summary['fps']:.2f} fps")
    for column in ("map", "keyframes", "point landmarks", "plane landmarks"):
        table.add_column(column, justify="right" if column != "map" else "left")
    for name, counts in summary["maps"].items():
        table.add_row(name, str(counts["keyframes"]), str(counts["point_landmarks"]), str(counts["plane_landmarks"]))
    shown: list = [table]
    for item in summary.get("objects", []):
        shown.append(f"object {item['id']}: detected at frame {item['created_at_frame']}, "
                     f"tracked in {item['frames_tracked']} frames")
    by_depth = summary.get("frames_by_depth", 0)
    carried = f", {by_depth} placed by their depth" if by_depth else ""
    shown.append(f"tracked {summary['frames_tracked']} of {summary['frames_processed']} frames "
                 f"({summary['frames_lost']} lost, {summary['relocalisations']} relocalisations{carried}); results in "
                 f"{escape(str(out_dir))}")
    return shown


def metrics_report(metrics: dict) -> list:
    """``jsr evaluate``'s metrics: the camera table, the objects table (within 80 columns), masks."""
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
            shown_value = value * 100.0 if unit == "cm" else value
            table.add_row(label, f"{shown_value:.3f} {unit}")
    for key in ("frames_associated", "gt_frames_without_estimate"):
        if key in camera:
            table.add_row(key.replace("_", " "), str(camera[key]))
    shown: list = [table]
    objects = metrics.get("objects") or {}
    matches = objects.get("matches") or []
    if matches:
        # Short headers, units in the caption: the table fits an 80-column terminal.
        table = Table(title="Objects", caption="t: translation error, cm; R: rotation error, deg; tracked: share of "
                      "the frames it is visible in; more maps: further maps of the same object")
        for column in ("map", "true", "frames", "t RMSE", "t med", "R RMSE", "tracked", "more maps", "all maps"):
            table.add_column(column, justify="right")
        for match in matches:
            table.add_row(
                str(match.get("estimated_id")),
                str(match.get("true_id")),
                str(match.get("frames")),
                figure(match.get("translation_rmse_cm")),
                figure(match.get("translation_median_cm")),
                figure(match.get("rotation_rmse_deg")),
                figure(match.get("tracked_share")),
                ", ".join(str(k) for k in match.get("further_maps", [])) or "-",
                figure(match.get("tracked_share_all_maps")),
            )
        shown.append(table)
    masks = metrics.get("masks")
    if masks:
        shown.append(f"masks: precision {masks.get('precision', float('nan')):.3f}, "
                     f"recall {masks.get('recall', float('nan')):.3f} over {masks.get('frames', 0)} frames")
    return shown


def rendered_report(rendered: dict) -> list:
    """What ``jsr render`` wrote."""
    return [f"rendered {len(rendered['files'])} previews in {rendered['seconds']:.1f} s:",
            *(f"  {escape(path)}" for path in rendered["files"])]


def batch_line(row: dict) -> str:
    """One line for a finished sequence of a batch."""
    name, status = escape(row["name"]), row["status"]
    if status == "failed":
        return f"[red]failed[/] {name}: {escape(row.get('error', ''))}"
    parts = [f"{row['frames']} frames" if row.get("frames") is not None else None,
             f"{row['fps']:.2f} fps" if row.get("fps") and status != "skipped" else None,
             f"ATE {row['ate_rmse_cm']:.2f} cm" if row.get("ate_rmse_cm") is not None else None,
             f"{row['objects_matched']} of {row['objects_true']} objects matched" if row.get("objects_true") else None]
    colour = {"complete": "green", "skipped": "cyan"}.get(status, "yellow")
    return f"[{colour}]{status}[/] {name}: " + ", ".join(part for part in parts if part)


def batch_counts(summary: dict) -> str:
    """``2 complete, 1 failed``."""
    return ", ".join(f"{count} {status}" for status, count in (summary.get("counts") or {}).items())


def batch_report(summary: dict, out: Path) -> list:
    """The batch summary: one table row per sequence, and the counts."""
    table = Table(title=f"jsr batch: {len(summary['sequences'])} sequences")
    for column in ("sequence", "status", "frames", "fps", "ATE cm", "objects", "t cm", "R deg"):
        # a long name folds onto a second line rather than losing its end in 80 columns
        table.add_column(column, justify="left" if column in ("sequence", "status") else "right",
                         overflow="fold" if column == "sequence" else "ellipsis")
    for row in summary["sequences"]:
        objects = f"{row['objects_matched']}/{row['objects_true']}" if row.get("objects_true") is not None else "-"
        table.add_row(escape(row["name"]), row["status"], str(row.get("frames") or "-"), figure(row.get("fps")),
                      figure(row.get("ate_rmse_cm")), objects, figure(row.get("object_t_rmse_cm_max")),
                      figure(row.get("object_r_rmse_deg_max")))
    return [table, f"{batch_counts(summary)}; summary in {escape(str(out / 'batch_summary.csv'))} and .json"]
