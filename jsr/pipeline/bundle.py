"""Per-map bundle adjustment (Section 2.4 of the paper) with scipy instead of Ceres.

The paper refines, for every map independently, "all the keyframe poses and landmark
locations" by minimising the registration error. Here one run works on a *window*: the last
``window_keyframes`` keyframes of the map are free, every landmark they observe is free, and
every other keyframe that observes one of those landmarks contributes its observations with
its pose held fixed. The first keyframe of a map is always fixed (it defines the map frame).
Keyframes that observe at least ``min_shared_landmarks`` common landmarks, and landmarks that
pin them, are linked; a group of free keyframes linked to no fixed keyframe has its oldest
keyframe held fixed, since the few landmarks it shares with the rest do not fix where the group
lies (:mod:`jsr.pipeline.bundle_links`).

Parameters (all increments from the current state, so ``x0 = 0``; the solver itself sees them
shifted by :data:`SOLVER_OFFSET`):

* keyframe: 6 per free keyframe, ``R = exp(w) R0`` (rotation vector ``w`` in the map frame,
  about the camera centre) and ``t = t0 + dt``;
* point landmark: 3, ``X = X0 + dX``;
* plane landmark: 3, the normal rotated by a 2D increment in its tangent plane
  (``n = exp(a1 b1 + a2 b2) n0``) and ``d = d0 + dd`` -- minimal, no unit-norm constraint.

Residuals, each divided by its sigma so that the Huber scale is in sigmas:

* 3D point observation, in the image as in tracking: the landmark reprojected into the keyframe
  minus where the keypoint was seen (2 components, pixels over ``pixel_sigma``) and the
  landmark's depth in the keyframe minus the measured depth (1 component) over
  ``sigma = max(min_inlier_threshold / inlier_sigmas, sigma_z)``, one sigma of the paper's
  inlier threshold ``max(1 cm, 3 sigma_Z)``. (An isotropic 3D residual weighed by the axial
  sigma made bundle adjustment raise ATE on real data: the depth error is systematic there);
* 2D point observation (no depth): reprojection of the landmark into the keyframe minus the
  keypoint pixel, over ``pixel_sigma``;
* plane observation: the keyframe's camera plane moved to the map frame minus the plane
  landmark: the normal difference (3) over ``plane_normal_sigma`` and the offset difference
  (1) over ``plane_offset_sigma``.

Each of these sigmas is then multiplied by a *variance component* estimated from the residuals
(``estimate_noise``, :mod:`~jsr.pipeline.bundle_noise`): on real footage the depth residuals
spread more than the sensor model says and the reprojections less.

``scipy.optimize.least_squares(method="trf")`` with a Huber loss
(:func:`~jsr.pipeline.robust_loss.huber_loss`: scipy's ``"huber"`` cost with
reweighted-least-squares curvature) solves it with an analytic sparse Jacobian
(:meth:`BundleProblem.jacobian`; each residual block touches one keyframe and one landmark).
Points seen by only one keyframe are not solved for: they carry no information on the poses
and follow their keyframe (:meth:`BundleProblem._carry_single_view_points`). On real footage
these two make a solve about four times faster than finite differences over every point.

Running it beside tracking, in a worker thread, is :mod:`jsr.pipeline.bundle_scheduler`.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

from jsr.config import BundleAdjustmentConfig, NoiseConfig
from jsr.geometry import invert_transform
from jsr.pipeline.bundle_solution import BundleResult, BundleSolution, apply_solution
from jsr.pipeline.bundle_jacobian import analytic_jacobian
from jsr.pipeline.bundle_links import link_spread, linked_groups
from jsr.pipeline.bundle_noise import (BOUNDS, GROUPS, MAX_PASSES, TOLERANCE, measured_spread, restore, reweigh,
                                       update, weights)
from jsr.pipeline.maps import Map
from jsr.pipeline.robust_loss import huber_cost, huber_loss

logger = logging.getLogger(__name__)

MIN_2D_DEPTH = 0.05
"""2D observations whose landmark is nearer than this (metres, along the optical axis) to the
keyframe at the start of a run are left out (they would project unstably)."""

FTOL = 1e-6
"""Relative cost change at which the solver stops (scipy's ``ftol``; its default 1e-8 adds
iterations that change the cost by less than a millionth)."""

SOLVER_OFFSET = 1.0
"""The solver's variables are the increments plus this constant (see :meth:`BundleProblem.solve`)."""


def _tangent_bases(normals: np.ndarray) -> np.ndarray:
    """``(Q, 3, 2)`` orthonormal bases of the planes orthogonal to unit ``normals`` ``(Q, 3)``."""
    helper = np.zeros_like(normals)
    use_x = np.abs(normals[:, 0]) < 0.9
    helper[use_x, 0] = 1.0
    helper[~use_x, 1] = 1.0
    first = np.cross(normals, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    second = np.cross(normals, first)
    return np.stack([first, second], axis=2)


class BundleProblem:
    """A self-contained copy of one window of a map: everything a solve needs.

    Built with :meth:`from_map` in the caller's thread; it holds no reference to the map, so it
    can be solved in another thread while the map keeps changing.

    Keyframes are numbered ``0..M-1`` inside the problem (``keyframe_indices`` maps them to
    positions in ``map.keyframes``); ``free_index[k]`` is the parameter block of keyframe ``k``
    or -1 if it is fixed.
    """

    def __init__(self):
        self.map_name = ""
        self.keyframe_indices = np.zeros(0, dtype=np.int64)
        self.free_index = np.zeros(0, dtype=np.int64)
        self.poses = np.zeros((0, 4, 4))
        self.point_ids = np.zeros(0, dtype=np.int64)
        self.positions = np.zeros((0, 3))
        self.plane_ids = np.zeros(0, dtype=np.int64)
        self.planes = np.zeros((0, 4))
        # 3D point observations
        self.obs3_keyframe = np.zeros(0, dtype=np.int64)
        self.obs3_point = np.zeros(0, dtype=np.int64)
        self.obs3_camera = np.zeros((0, 3))
        self.obs3_weight = np.zeros(0)
        # 2D point observations
        self.obs2_keyframe = np.zeros(0, dtype=np.int64)
        self.obs2_point = np.zeros(0, dtype=np.int64)
        self.obs2_pixels = np.zeros((0, 2))
        # plane observations (camera planes oriented like their landmark)
        self.obsp_keyframe = np.zeros(0, dtype=np.int64)
        self.obsp_plane = np.zeros(0, dtype=np.int64)
        self.obsp_camera = np.zeros((0, 4))
        # points observed by one keyframe only: not solved for, moved with that keyframe
        self.carried_point_ids = np.zeros(0, dtype=np.int64)
        self.carried_keyframes = np.zeros(0, dtype=np.int64)
        self.intrinsics = np.eye(3)
        self.pixel_weight = 1.0  # reprojection of points with depth
        self.pixel2d_weight = 1.0  # points without depth
        self.normal_weight = 100.0
        self.offset_weight = 100.0
        self.num_keyframes = 0
        self.num_points = 0
        self.num_planes = 0
        self._bases = np.zeros((0, 3, 2))

    # ------------------------------------------------------------------ building
    @classmethod
    def from_map(
        cls,
        map: Map,
        config: BundleAdjustmentConfig,
        noise: NoiseConfig,
        intrinsics_matrix: np.ndarray,
        window: int | None = None,
    ) -> "BundleProblem | None":
        """Gather the window of ``map``; None if there is nothing to optimise."""
        keyframes = map.keyframes
        total = len(keyframes)
        window = config.window_keyframes if window is None else int(window)
        first_free = max(1, total - window)  # keyframe 0 is never free
        if total < 2 or first_free >= total:
            return None
        problem = cls()
        problem.map_name = map.name
        problem.num_keyframes = total
        problem.num_points = len(map.points)
        problem.num_planes = len(map.planes)
        problem.intrinsics = np.asarray(intrinsics_matrix, dtype=float).copy()
        problem.pixel_weight = 1.0 / config.pixel_sigma
        problem.pixel2d_weight = 1.0 / config.pixel_sigma
        problem.normal_weight = 1.0 / config.plane_normal_sigma
        problem.offset_weight = 1.0 / config.plane_offset_sigma

        window_frames = range(max(0, total - window), total)
        # free landmarks: active points and all planes seen by the window
        seen_points = np.concatenate([keyframes[i].point_landmarks for i in window_frames]).astype(np.int64)
        point_ids = np.unique(seen_points)
        point_ids = point_ids[map.points.active[point_ids]]
        plane_ids = np.unique(np.concatenate(
            [np.asarray(keyframes[i].plane_landmarks, dtype=np.int64) for i in window_frames]))

        # every observation of those landmarks, from any keyframe (vectorised over observations)
        point_slot = np.full(len(map.points), -1, dtype=np.int64)
        point_slot[point_ids] = np.arange(len(point_ids))
        plane_slot = np.full(len(map.planes), -1, dtype=np.int64)
        plane_slot[plane_ids] = np.arange(len(plane_ids))
        counts = np.array([len(kf.point_landmarks) for kf in keyframes])
        obs_frame = np.repeat(np.arange(total), counts)
        obs_landmark = np.concatenate([kf.point_landmarks for kf in keyframes]).astype(np.int64)
        obs_camera = np.concatenate([kf.camera_points for kf in keyframes]).reshape(-1, 3)
        obs_pixels = np.concatenate([kf.pixels for kf in keyframes]).reshape(-1, 2)
        obs_sigma = np.concatenate([kf.sigma_z for kf in keyframes]).astype(float)
        keep = point_slot[obs_landmark] >= 0
        plane_counts = np.array([len(kf.plane_landmarks) for kf in keyframes])
        pobs_frame = np.repeat(np.arange(total), plane_counts)
        pobs_landmark = np.concatenate([np.asarray(kf.plane_landmarks, dtype=np.int64) for kf in keyframes])
        pobs_camera = np.concatenate([np.asarray(kf.camera_planes, dtype=float).reshape(-1, 4) for kf in keyframes])
        pkeep = plane_slot[pobs_landmark] >= 0 if len(pobs_landmark) else np.zeros(0, dtype=bool)

        # keyframes in the problem: the window plus fixed ones that observe its landmarks
        involved = np.zeros(total, dtype=bool)
        involved[window_frames.start:] = True
        involved[obs_frame[keep]] = True
        involved[pobs_frame[pkeep]] = True
        frames = np.flatnonzero(involved)
        frame_slot = np.full(total, -1, dtype=np.int64)
        frame_slot[frames] = np.arange(len(frames))
        free = frames >= first_free
        # gauge: every group of free keyframes must be tied to a fixed keyframe
        def pins(older: int, newer: int, shared_points: np.ndarray, shared_planes: np.ndarray) -> bool:
            keyframe = keyframes[frames[newer]]
            own = keyframe.point_landmarks[map.points.active[keyframe.point_landmarks]]
            spread = link_spread(map.points.positions[shared_points], map.planes.planes[shared_planes, :3],
                                 map.points.positions[own], keyframe.T_map_cam, noise, config)
            return spread <= config.link_max_spread

        linked = linked_groups(len(frames), frame_slot[obs_frame[keep]], obs_landmark[keep],
                               frame_slot[pobs_frame[pkeep]], pobs_landmark[pkeep], config.min_shared_landmarks,
                               pins if config.link_max_spread > 0 else None)
        for group in np.unique(linked):
            members = np.flatnonzero(linked == group)
            if free[members].all():
                oldest = int(members[0])
                free[oldest] = False
                logger.debug("%s: keyframes %s are linked to no fixed keyframe by %d common landmarks that pin them; "
                             "holding keyframe %d fixed", map.name, frames[members].tolist(),
                             config.min_shared_landmarks, int(frames[oldest]))
        if not free.any():
            return None
        problem.keyframe_indices = frames
        problem.free_index = np.where(free, np.cumsum(free) - 1, -1)
        problem.poses = np.stack([np.asarray(keyframes[i].T_map_cam, dtype=float) for i in frames])
        problem.point_ids = point_ids
        problem.positions = map.points.positions[point_ids].copy()
        problem.plane_ids = plane_ids
        problem.planes = map.planes.planes[plane_ids].copy().reshape(-1, 4)
        problem._bases = _tangent_bases(problem.planes[:, :3]) if len(plane_ids) else np.zeros((0, 3, 2))

        obs_frame, obs_landmark = obs_frame[keep], obs_landmark[keep]
        obs_camera, obs_pixels, obs_sigma = obs_camera[keep], obs_pixels[keep], obs_sigma[keep]
        has_depth = np.all(np.isfinite(obs_camera), axis=1)
        floor = noise.min_inlier_threshold / noise.inlier_sigmas
        problem.obs3_keyframe = frame_slot[obs_frame[has_depth]]
        problem.obs3_point = point_slot[obs_landmark[has_depth]]
        problem.obs3_camera = obs_camera[has_depth].copy()
        problem.obs3_weight = 1.0 / np.maximum(floor, obs_sigma[has_depth])
        # where the measurement was seen: normalised image coordinates of the camera point
        problem.obs3_uv = problem.obs3_camera[:, :2] / problem.obs3_camera[:, 2:3]

        kf2 = frame_slot[obs_frame[~has_depth]]
        pt2 = point_slot[obs_landmark[~has_depth]]
        depth = problem._camera_points(problem.poses[kf2, :3, :3], problem.poses[kf2, :3, 3], problem.positions[pt2])[:, 2]
        ahead = depth > MIN_2D_DEPTH
        problem.obs2_keyframe, problem.obs2_point = kf2[ahead], pt2[ahead]
        problem.obs2_pixels = obs_pixels[~has_depth][ahead].copy()

        problem.obsp_keyframe = frame_slot[pobs_frame[pkeep]]
        problem.obsp_plane = plane_slot[pobs_landmark[pkeep]]
        camera_planes = pobs_camera[pkeep].copy()
        if len(camera_planes):
            rotations = problem.poses[problem.obsp_keyframe, :3, :3]
            map_normals = np.einsum("nij,nj->ni", rotations, camera_planes[:, :3])
            flip = np.sum(map_normals * problem.planes[problem.obsp_plane, :3], axis=1) < 0
            camera_planes[flip] *= -1.0  # same plane, opposite orientation (as PlaneLandmarks.fuse)
        problem.obsp_camera = camera_planes
        problem._carry_single_view_points()
        return problem

    def _carry_single_view_points(self) -> None:
        """Take the points observed by one keyframe of the problem out of the solve.

        Why: a point seen once has as many free coordinates as its observation has residuals
        (3 with depth; 2 without, plus its depth along the ray), so at the optimum it sits
        exactly on its observation and says nothing about any pose. Solving for it only costs
        (on real footage 60-80% of a window's points are seen once). Instead it moves rigidly
        with its keyframe's correction when the solution is applied, which is where the full
        solve would put it."""
        counts = np.bincount(np.concatenate([self.obs3_point, self.obs2_point]), minlength=len(self.point_ids))
        solved = counts >= 2
        if solved.all():
            return
        single = np.flatnonzero(~solved)
        # the one keyframe slot that observes each single-view point
        slot_of_point = np.full(len(self.point_ids), -1, dtype=np.int64)
        slot_of_point[self.obs3_point] = self.obs3_keyframe
        slot_of_point[self.obs2_point] = self.obs2_keyframe
        observed = slot_of_point[single] >= 0  # a point whose only observation was dropped stays as it is
        self.carried_point_ids = self.point_ids[single[observed]]
        self.carried_keyframes = self.keyframe_indices[slot_of_point[single[observed]]]

        new_slot = np.full(len(self.point_ids), -1, dtype=np.int64)
        new_slot[solved] = np.arange(int(solved.sum()))
        keep3, keep2 = solved[self.obs3_point], solved[self.obs2_point]
        self.obs3_keyframe, self.obs3_point = self.obs3_keyframe[keep3], new_slot[self.obs3_point[keep3]]
        self.obs3_camera, self.obs3_weight = self.obs3_camera[keep3], self.obs3_weight[keep3]
        self.obs3_uv = self.obs3_uv[keep3]
        self.obs2_keyframe, self.obs2_point = self.obs2_keyframe[keep2], new_slot[self.obs2_point[keep2]]
        self.obs2_pixels = self.obs2_pixels[keep2]
        self.point_ids, self.positions = self.point_ids[solved], self.positions[solved]

    # ------------------------------------------------------------------ sizes
    @property
    def num_free_keyframes(self) -> int:
        return int(np.sum(self.free_index >= 0))

    @property
    def num_parameters(self) -> int:
        return 6 * self.num_free_keyframes + 3 * len(self.point_ids) + 3 * len(self.plane_ids)

    @property
    def num_observations(self) -> int:
        return len(self.obs3_keyframe) + len(self.obs2_keyframe) + len(self.obsp_keyframe)

    @property
    def num_residuals(self) -> int:
        return 3 * len(self.obs3_keyframe) + 2 * len(self.obs2_keyframe) + 4 * len(self.obsp_keyframe)

    # ------------------------------------------------------------------ model
    def unpack(self, x: np.ndarray):
        """Rotations ``(M, 3, 3)``, translations ``(M, 3)``, positions ``(P, 3)``, planes ``(Q, 4)``."""
        free_count = self.num_free_keyframes
        point_count = len(self.point_ids)
        pose_x = x[: 6 * free_count].reshape(-1, 6)
        point_x = x[6 * free_count : 6 * free_count + 3 * point_count].reshape(-1, 3)
        plane_x = x[6 * free_count + 3 * point_count :].reshape(-1, 3)
        rotations = self.poses[:, :3, :3].copy()
        translations = self.poses[:, :3, 3].copy()
        if free_count:
            free = self.free_index >= 0
            increments = Rotation.from_rotvec(pose_x[:, :3]).as_matrix()
            rotations[free] = increments @ rotations[free]
            translations[free] += pose_x[:, 3:]
        positions = self.positions + point_x
        planes = self.planes.copy()
        if len(planes):
            rotvecs = np.einsum("qij,qj->qi", self._bases, plane_x[:, :2])
            planes[:, :3] = Rotation.from_rotvec(rotvecs).apply(self.planes[:, :3])
            planes[:, 3] += plane_x[:, 2]
        return rotations, translations, positions, planes

    @staticmethod
    def _camera_points(rotations: np.ndarray, translations: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Map-frame ``points`` into the cameras ``(R, t)`` (one per row): ``R^T (X - t)``."""
        return np.einsum("nji,nj->ni", rotations, points - translations)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Whitened residual vector: 3D points, then 2D points, then planes."""
        rotations, translations, positions, planes = self.unpack(x)
        parts = []
        if len(self.obs3_keyframe):
            # Image-space, as in tracking: reprojection of the landmark against where the
            # keypoint was seen (pixels over pixel_sigma) and its depth against the measured
            # depth (over sigma_Z). The sensor's lateral accuracy is far better than its depth.
            k = self.obs3_keyframe
            local = self._camera_points(rotations[k], translations[k], positions[self.obs3_point])
            z = np.maximum(local[:, 2], 1e-3)
            focal = 0.5 * (self.intrinsics[0, 0] + self.intrinsics[1, 1])
            reprojection = (local[:, :2] / z[:, None] - self.obs3_uv) * (focal * self.pixel_weight)
            depth = (local[:, 2] - self.obs3_camera[:, 2]) * self.obs3_weight
            parts.append(np.column_stack([reprojection, depth]).ravel())
        if len(self.obs2_keyframe):
            k = self.obs2_keyframe
            local = self._camera_points(rotations[k], translations[k], positions[self.obs2_point])
            z = np.maximum(local[:, 2], 1e-3)
            f = self.intrinsics
            u = f[0, 0] * local[:, 0] / z + f[0, 1] * local[:, 1] / z + f[0, 2]
            v = f[1, 1] * local[:, 1] / z + f[1, 2]
            parts.append(((np.column_stack([u, v]) - self.obs2_pixels) * self.pixel2d_weight).ravel())
        if len(self.obsp_keyframe):
            k = self.obsp_keyframe
            normals = np.einsum("nij,nj->ni", rotations[k], self.obsp_camera[:, :3])
            offsets = self.obsp_camera[:, 3] - np.sum(normals * translations[k], axis=1)
            landmark = planes[self.obsp_plane]
            parts.append(np.column_stack([
                (normals - landmark[:, :3]) * self.normal_weight,
                (offsets - landmark[:, 3]) * self.offset_weight,
            ]).ravel())
        return np.concatenate(parts) if parts else np.zeros(0)

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        """Analytic ``(num_residuals, num_parameters)`` Jacobian of :meth:`residuals` at ``x``."""
        return analytic_jacobian(self, x)

    # ------------------------------------------------------------------ solving
    def _least_squares(self, x_start: np.ndarray, config: BundleAdjustmentConfig
                       ) -> tuple[np.ndarray | None, float, int, str]:
        """One robust solve from the increments ``x_start`` under the current weights:
        ``(x, cost, residual evaluations, message)``, ``x`` None when the solver failed or did
        not lower the cost."""
        start_cost = huber_cost(self.residuals(x_start), config.huber_sigmas)
        try:
            # The solver sees increments + SOLVER_OFFSET: scipy's first trust radius is
            # |x0| in scaled units (1 when x0 = 0), which would cost ~7 doubling iterations.
            solution = least_squares(
                lambda y: self.residuals(y - SOLVER_OFFSET), x_start + SOLVER_OFFSET,
                jac=lambda y: self.jacobian(y - SOLVER_OFFSET), method="trf", loss=huber_loss, f_scale=config.huber_sigmas,
                x_scale="jac", max_nfev=config.max_iterations, ftol=FTOL,
            )
        except (ValueError, np.linalg.LinAlgError) as error:
            return None, start_cost, 0, f"solver failed: {error}"
        final = float(solution.cost)
        # status 0 is "max_nfev reached": still an improvement worth keeping
        if solution.status >= 0 and np.all(np.isfinite(solution.x)) and final <= start_cost:
            return solution.x - SOLVER_OFFSET, final, int(solution.nfev), str(solution.message)
        return None, start_cost, int(solution.nfev), f"rejected: {solution.message} (cost {start_cost:.6g} -> {final:.6g})"

    def solve(self, config: BundleAdjustmentConfig, noise_components: np.ndarray | None = None,
              estimate: bool | None = None) -> BundleSolution:
        """Run the robust least-squares; never touches a map. Each group's sigma is
        ``noise_components`` ``(5,)`` times the configured one (the configured one when None).
        With ``estimate`` (default ``config.estimate_noise``) the components are re-estimated
        from the residuals between solves (:mod:`~jsr.pipeline.bundle_noise`); the costs are
        then those under the first and the last solve's sigmas."""
        started = time.perf_counter()
        cpu_started = time.thread_time()
        estimate = config.estimate_noise if estimate is None else estimate
        components = (np.ones(len(GROUPS)) if noise_components is None
                      else np.clip(np.nan_to_num(np.asarray(noise_components, float), nan=1.0), *BOUNDS))
        configured = weights(self)  # put back at the end: a solve leaves the problem as it was
        reweigh(self, components)
        x = np.zeros(self.num_parameters)
        initial_cost = huber_cost(self.residuals(x), config.huber_sigmas)
        final_cost, iterations, success, passes, message = initial_cost, 0, False, 0, ""
        solves = MAX_PASSES if estimate else 1
        if self.num_residuals < self.num_parameters:
            message = f"underdetermined: {self.num_residuals} residuals for {self.num_parameters} parameters"
            solves = 0
        for _ in range(solves):
            solved, cost, evaluations, outcome = self._least_squares(x, config)
            iterations += evaluations
            if solved is None:  # keep the last solve that succeeded, if any
                message = f"{message}; solve {passes + 1}: {outcome}" if success else outcome
                break
            x, final_cost, success, passes, message = solved, cost, True, passes + 1, outcome
            if not estimate:
                break
            estimated = update(components, measured_spread(self, x))
            change = estimated / components
            reweigh(self, change)
            components = estimated
            if float(np.max(np.abs(change - 1.0))) <= TOLERANCE:
                break
        restore(self, configured)
        rotations, translations, positions, planes = self.unpack(x)
        after = self.poses.copy()
        after[:, :3, :3] = rotations
        after[:, :3, 3] = translations
        free = self.free_index >= 0
        newest = np.flatnonzero(free)[-1]
        correction = after[newest] @ invert_transform(self.poses[newest])
        result = BundleResult(
            success=success,
            initial_cost=initial_cost,
            final_cost=final_cost,
            keyframes_optimised=int(free.sum()),
            landmarks_optimised=len(self.point_ids),
            observations=self.num_observations,
            iterations=iterations,
            seconds=time.perf_counter() - started,
            cpu_seconds=time.thread_time() - cpu_started,
            planes_optimised=len(self.plane_ids),
            keyframes_fixed=int((~free).sum()),
            points_carried=len(self.carried_point_ids),
            message=message,
            correction=correction,
            noise_components=components,
            passes=passes,
        )
        logger.debug("%s: bundle adjustment %s: %d keyframes (+%d fixed), %d points (+%d seen once, carried), "
                     "%d planes, %d observations, cost %.4g -> %.4g in %d evaluations and %d solves, %.3f s; "
                     "sigmas x %s (%s)", self.map_name, "done" if success else "failed", result.keyframes_optimised,
                     result.keyframes_fixed, result.landmarks_optimised, result.points_carried, result.planes_optimised,
                     result.observations, initial_cost, final_cost, iterations, passes, result.seconds,
                     np.array2string(components, precision=2), ", ".join(GROUPS))
        return BundleSolution(
            result=result,
            keyframe_indices=self.keyframe_indices[free],
            poses_before=self.poses[free],
            poses_after=after[free],
            point_ids=self.point_ids,
            positions_before=self.positions,
            positions_after=positions,
            plane_ids=self.plane_ids,
            planes_before=self.planes,
            planes_after=planes,
            carried_point_ids=self.carried_point_ids,
            carried_keyframes=self.carried_keyframes,
            num_keyframes=self.num_keyframes,
            num_points=self.num_points,
            num_planes=self.num_planes,
        )


def _skipped(message: str) -> BundleResult:
    return BundleResult(False, 0.0, 0.0, 0, 0, 0, 0, 0.0, message=message)


def bundle_adjust(
    map: Map,
    config: BundleAdjustmentConfig,
    noise: NoiseConfig,
    intrinsics_matrix: np.ndarray,
    window: int | None = None,
) -> BundleResult:
    """Refine the last ``window`` (default ``config.window_keyframes``) keyframes of ``map`` and
    the landmarks they observe, in place; returns a summary. Does nothing when disabled."""
    if not config.enabled:
        return _skipped("disabled")
    problem = BundleProblem.from_map(map, config, noise, intrinsics_matrix, window)
    if problem is None:
        return _skipped("nothing to optimise")
    solution = problem.solve(config)
    apply_solution(map, solution)
    return solution.result
