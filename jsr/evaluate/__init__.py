"""Evaluation of a results folder against a sequence's ground truth.

Metrics:

* camera: absolute trajectory error (ATE) of the positions after a rigid (SE(3), no scale)
  Umeyama alignment, relative pose error (RPE) over consecutive associated frames, and
  tracking coverage.
* objects: per estimated/true object pair, the pose error of the object *in the camera
  frame* (this removes the unknown alignment of the two worlds) after removing the constant
  offset between the estimated and the true object frames, its translation measured at the
  true object's origin (its centre); estimated objects are matched
  greedily to true ones by lowest median translation error.
* masks: pixel precision and recall of "moving object" against the labels, overall and per
  matched object pair.

Modules: :mod:`~jsr.evaluate.trajectory` (pose association, ATE, RPE),
:mod:`~jsr.evaluate.objects` (object pose errors and matching), :mod:`~jsr.evaluate.masks`
(mask precision/recall), :mod:`~jsr.evaluate.stats` (JSON-safe numbers, angles, RMS) and
:mod:`~jsr.evaluate.run` (a results folder read into metrics). The package exposes the
entry points users call.
"""

from jsr.evaluate.run import evaluate_run, write_metrics

__all__ = ["evaluate_run", "write_metrics"]
