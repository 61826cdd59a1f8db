"""Seeded, deterministic synthetic RGB-D sequences with exact ground truth.

A textured room (floor, walls, ceiling) with a table, a cabinet, a shelf with books, a
ball and a bin, plus ``K`` rigid textured objects resting on the table top and moved
between views ("jump"), continuously ("smooth") or never ("static"). A hand-held-like
camera circles the table. Every frame is ray cast with Open3D's ``RaycastingScene``.

Written in the TUM RGB-D layout that :func:`jsr.io.dataset.open_sequence` reads::

    OUT/rgb/<ts>.png|jpg, OUT/depth/<ts>.png (16 bit, 5000 per metre), OUT/labels/<ts>.png
    OUT/rgb.txt, OUT/depth.txt, OUT/groundtruth.txt (T_w_c), OUT/objects/object_<k>.txt (T_w_o)
    OUT/camera.yaml, OUT/synth.yaml (options and version)

Labels are 0 for the static scene and ``k`` for object ``k`` (1-based). The world frame is
the room frame: z up, floor at z = 0, table centre above the origin. Object origins are the
object centres.

Randomness: every draw comes from generators derived from ``options.seed`` with
:class:`numpy.random.SeedSequence` spawn keys (plan, per-texture-tile, per-frame), so a
result does not depend on the order in which frames or textures are computed.

Composites (:func:`generate_composite`, ``jsr synth OUT --background SEQ``) put the same
objects, textures, sensor model and motion schedules into frames of a real sequence with
ground-truth camera poses, by depth test, on a surface found in its depth.

Modules: :mod:`~jsr.synth.options` (what to render, validation), :mod:`~jsr.synth.randomness`
(the seeded streams), :mod:`~jsr.synth.scene` (geometry, camera path),
:mod:`~jsr.synth.motion` (motion schedules, object placement on a support surface),
:mod:`~jsr.synth.textures` (procedural textures), :mod:`~jsr.synth.render` (ray casting and
the depth sensor model), :mod:`~jsr.synth.write` (the sequence folder); for composites
:mod:`~jsr.synth.background` (the real sequence and its ground truth),
:mod:`~jsr.synth.support` (the surface objects rest on, visibility) and
:mod:`~jsr.synth.composite` (depth test, the composite's folder). The package exposes the
entry points users call.
"""

from jsr.synth.composite import generate_composite
from jsr.synth.options import CompositeOptions, SynthOptions, validate_composite_options, validate_options
from jsr.synth.write import check_output_folder, generate_sequence

__all__ = [
    "CompositeOptions",
    "SynthOptions",
    "check_output_folder",
    "generate_composite",
    "generate_sequence",
    "validate_composite_options",
    "validate_options",
]
