"""Virtual lab: synthetic recording sessions with a known truth.

Replays the experiment of Wu et al. 2020 (Sec. 4) in software: a dVRK PSM pokes the top
and the sides of a 68.7 x 39.3 x 35.8 mm, 104.01 g gel block; an SR300-like depth camera
records it at 30 Hz while the robot reports kinematics at ~1 kHz; a calibration touches
the four top corners. The phantom's deformation comes from a truth simulation that is
more faithful than the replay model (finer mesh, stable Neo-Hookean material, Smith et
al. 2018) plus any effect of ``SESSION_FORMAT.md`` that is switched on; with a
:class:`core.lab.variation.LabVariation` (the ``field`` preset) the truth's law, modulus,
mesh, contact, damping and noise levels are drawn per seed. The probe follows random
pokes, or given paths (``paths=``). The session is streamed to disk through
:class:`core.io.SessionWriter`, with ``truth.json``.

Frames: *phantom* (box ``[0, size]``, z up), *robot* (kinematics, corners, forces;
``T_phantom_robot`` maps robot points into the phantom frame) and *camera* (clouds;
OpenCV axes; ``T_phantom_camera`` maps camera points into the phantom frame).

This module holds the entry, :func:`generate_session` (the preset and the given paths
checked, the session-wide draws, the sequences planned, the truth simulated ahead in
worker processes, everything written in order, ``truth.json``), and re-exports the
public names of the modules it is built from: :mod:`core.lab.config` (:class:`LabConfig`,
the presets, the effects, :class:`LabError`), :mod:`core.lab.phantom` (the phantom, its
size and mass), :mod:`core.lab.truth` (the truth simulation), :mod:`core.lab.rendering`
(the camera rig, its clock and clouds) and :mod:`core.lab.robot` (robot pose, calibration
touches, kinematics).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from core.errors import TissueTwinError
from core.lab.camera import Instrument
from core.lab.config import (
    DEMO_EFFECTS,
    INPUT_EFFECTS,
    PHYSICAL_EFFECTS,
    PRESET_NOTES,
    PRESETS,
    LabConfig,
    LabError,
    ProgressCallback,
    complete_effects,
)
from core.lab.phantom import PHANTOM_DENSITY, PHANTOM_MASS, PHANTOM_SIZE, make_phantom
from core.lab.probing import ProbePlan, plan_from_path, plan_sequence
from core.lab.rendering import frame_times, place_camera
from core.lab.robot import quat_xyzw, random_robot_pose, recorded_kinematics, write_calibration
from core.lab.surface_probing import plan_surface_sequence
from core.lab.truth import MODEL_CACHE, TRUTH_RETRIES, SimJob, material_truth, rest_positions, run_sim, truth_mesh
from core.lab.variation import apply_variation

__all__ = [
    "GENERATOR_NAME",
    "GENERATOR_VERSION",
    "PHANTOM_SIZE",
    "PHANTOM_MASS",
    "LabConfig",
    "LabError",
    "PRESETS",
    "PRESET_NOTES",
    "DEMO_EFFECTS",
    "PHYSICAL_EFFECTS",
    "INPUT_EFFECTS",
    "complete_effects",
    "generate_session",
]

GENERATOR_NAME = "tissuetwin-lab"
GENERATOR_VERSION = "0.1.0"


# --------------------------------------------------------------------------------------
# the generator
# --------------------------------------------------------------------------------------


@dataclass
class _Sequence:
    name: str
    role: str
    duration: float
    plan: ProbePlan
    frame_times: np.ndarray
    kin_t: np.ndarray
    rng: np.random.Generator


def generate_session(
    out: str | Path,
    *,
    preset: str | LabConfig = "small",
    seed: int = 0,
    effects: Sequence[dict] = (),
    with_force: bool = False,
    overwrite: bool = False,
    callback: ProgressCallback | None = None,
    paths: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
    shape: str = "box",
    phantom_stl: str | Path | None = None,
) -> Path:
    """Generate a synthetic session folder (``tissue-session/1`` plus ``truth.json``).

    Args:
        out: the session folder to create.
        preset: a name of :data:`PRESETS` ("small", "demo", "field", "paper") or a
            :class:`LabConfig`.
        seed: all randomness comes from ``numpy.random.default_rng(seed)`` (and, for a
            config with ``variation``, the lab's draws from ``default_rng([seed, 7])``, so
            that poses, plans and noise streams do not depend on it); the same seed and
            arguments give byte-identical files.
        effects: effect dicts of ``SESSION_FORMAT.md`` (``{"kind": "gravity", "g": [...]}``);
            missing parameters take the defaults of :mod:`core.simulation.effects`.
            Positions are in the phantom frame.
        with_force: add ``fx, fy, fz`` (N, robot frame) to kinematics.csv: the contact
            force of the truth simulation at the camera frames, interpolated to the
            kinematic times, plus ``force_noise``.
        overwrite: replace an existing session at ``out``.
        callback: ``callback(fraction in [0, 1], message)`` for progress.
        paths: optional given probe paths, one ``(t (K,) s, centres (K, 3) m)`` per
            sequence (as many as ``cfg.sequence_roles``): the true sphere-centre path in
            the phantom frame, linearly interpolated, t strictly increasing from t[0] >= 0
            (held at the first point before). Each sequence then follows its path instead
            of a random plan and lasts its path's last time (overriding
            ``cfg.sequence_durations``); it has no pokes (``"pokes": []`` in truth.json)
            and its tool's shaft leans 25 degrees from vertical away from the camera,
            unrolled (:func:`core.lab.probing.plan_from_path`). Camera, noise, calibration,
            effects (input effects too) and force columns are as for random plans.
        shape: "box" (the paper's 68.7 x 39.3 x 35.8 mm block on a node grid), "dome"
            or "kidney" (:mod:`core.lab.shapes`). Other shapes are written as
            ``phantom.stl``; their truth is the STL filled by Gmsh with about as many
            nodes as ``cfg.grid`` holds; the mass is the paper's gel density times the
            volume; pokes go anywhere on the reachable surface
            (:func:`core.lab.surface_probing.plan_surface_sequence`); calibration touches
            five named landmarks (``calibration/landmarks.csv``) instead of corners.
        phantom_stl: a watertight STL (metres, z up, resting on z = 0) to use as the
            phantom instead of ``shape`` (shifted in x and y so that its bounding box
            starts at 0).

    Returns:
        the session folder.

    Raises:
        LabError: unknown preset or shape, bad effect, a bad path (count, shapes, times,
            or deeper than 15 mm into the phantom), a bad STL, or a truth simulation
            that diverged.
        core.io.SessionExistsError: ``out`` exists and ``overwrite`` is false.
    """
    from core.io import (
        CameraSpec,
        PhantomSpec,
        ProbeSpec,
        SequenceSpec,
        SessionMeta,
        SessionWriter,
    )

    if isinstance(preset, LabConfig):
        cfg, preset_name = preset, "custom"
    elif preset in PRESETS:
        cfg, preset_name = PRESETS[preset], preset
    else:
        raise LabError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)} or a LabConfig")
    if len(cfg.sequence_durations) != len(cfg.sequence_roles) or not cfg.sequence_durations:
        raise LabError(f"sequence_durations ({len(cfg.sequence_durations)}) and sequence_roles "
                       f"({len(cfg.sequence_roles)}) must have the same non-zero length")
    if paths is not None:
        paths = list(paths)
        if len(paths) != len(cfg.sequence_roles):
            raise LabError(f"got {len(paths)} probe paths for {len(cfg.sequence_roles)} sequences "
                           f"(roles {cfg.sequence_roles}); give one (t, centres) per sequence")
        durations = []
        for i, path in enumerate(paths):
            if not isinstance(path, (tuple, list)) or len(path) != 2:
                raise LabError(f"probe path {i} must be a pair (t (K,) s, centres (K, 3) m), got {type(path).__name__}")
            try:
                t_i = np.asarray(path[0], dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise LabError(f"probe path {i}: times must be numbers, {exc}") from exc
            if t_i.ndim != 1 or t_i.size < 2:
                raise LabError(f"probe path {i}: times must be (K,) with K >= 2, got shape {t_i.shape}")
            durations.append(float(t_i[-1]))
        cfg = replace(cfg, sequence_durations=tuple(durations))
    report = callback or (lambda fraction, message: None)
    t_wall = time.perf_counter()
    full_effects = complete_effects(effects)
    by_kind = {e["kind"]: e for e in full_effects}
    physical = tuple(e for e in full_effects if e["kind"] in PHYSICAL_EFFECTS)
    r_nominal = float(cfg.probe_radius)
    r_true = float(by_kind["probe_radius"]["radius"]) if "probe_radius" in by_kind else r_nominal
    time_offset = float(by_kind["time_offset"]["offset"]) if "time_offset" in by_kind else 0.0
    kin_offset = (np.asarray(by_kind["kinematic_offset"]["offset"], float)
                  if "kinematic_offset" in by_kind else np.zeros(3))
    import shutil
    import tempfile

    workdir = Path(tempfile.mkdtemp(prefix="tissuetwin-lab-"))
    try:
        phantom = make_phantom(shape, phantom_stl, workdir)
    except BaseException:
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    size = phantom.size
    reachable = None
    if phantom.surface is not None:
        from core.lab.surface_probing import ReachableSurface

        reachable = ReachableSurface(*phantom.surface)
        if "inclusion" in by_kind:
            inc = by_kind["inclusion"]
            if float(reachable.clearance(np.asarray(inc["center"], float)[None])[0]) >= 0.0:
                shutil.rmtree(workdir, ignore_errors=True)
                raise LabError(f"the inclusion's centre {inc['center']} m lies outside the {shape if phantom_stl is None else 'STL'} "
                               f"phantom (bounds {np.round(reachable.mesh.bounds, 4).tolist()} m): give a centre inside it")

    # ---- session-wide draws, in a fixed order -----------------------------------------
    rng = np.random.default_rng(seed)
    if cfg.youngs_modulus_range is not None:
        lo, hi = cfg.youngs_modulus_range
        E = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    else:
        E = float(cfg.youngs_modulus)
    drawn = None
    if cfg.variation is not None:
        # a generator of its own: the main stream (poses, plans, noise) stays the seed's
        drawn = cfg.variation.draw(np.random.default_rng([int(seed), 7]))
        cfg = apply_variation(cfg, drawn)
        E = float(cfg.youngs_modulus)
    T_phantom_robot = random_robot_pose(rng, cfg.robot_distance_range)
    T_robot_phantom = np.linalg.inv(T_phantom_robot)
    top_centre = np.array([size[0] / 2, size[1] / 2, size[2]])
    rig = place_camera(rng, cfg, size, top_centre)
    T_phantom_camera, intrinsics = rig.T_phantom_camera, rig.intrinsics
    cam_dir = T_phantom_camera[:2, 3] - top_centre[:2]
    cam_azimuth = float(np.arctan2(cam_dir[1], cam_dir[0]))
    corner_rng, reference_rng, *seq_rngs = rng.spawn(2 + len(cfg.sequence_durations))

    sequences: list[_Sequence] = []
    for i, (dur, role) in enumerate(zip(cfg.sequence_durations, cfg.sequence_roles)):
        srng = seq_rngs[i]
        # the instrument comes from the side opposite the camera, as in the paper's Fig. 2
        if paths is None:
            azimuth = cam_azimuth + np.pi + srng.uniform(-np.pi / 3, np.pi / 3)
            try:
                if reachable is None:
                    plan = plan_sequence(srng, size=size, radius=r_true, duration=float(dur), config=cfg.probing,
                                         tool_azimuth=azimuth)
                else:
                    plan = plan_surface_sequence(srng, surface=reachable, radius=r_true, duration=float(dur),
                                                 config=cfg.probing, tool_azimuth=azimuth)
            except ValueError as exc:
                raise LabError(f"sequence seq{i:02d} ({role}, {dur} s): {exc}") from exc
        else:
            try:
                plan = plan_from_path(paths[i][0], paths[i][1], size=size, radius=r_true,
                                      tool_azimuth=cam_azimuth + np.pi)
            except ValueError as exc:
                raise LabError(f"probe path {i} ({role} sequence seq{i:02d}): {exc}") from exc
        ft = frame_times(srng, float(dur), cfg.camera_rate_hz, cfg.frame_jitter)
        if ft.size == 0:
            raise LabError(f"sequence seq{i:02d} lasts {dur} s: too short for one camera frame at "
                           f"{cfg.camera_rate_hz} Hz")
        kt = np.arange(int(np.floor(dur * cfg.kinematics_rate_hz)) + 1) / cfg.kinematics_rate_hz
        sequences.append(_Sequence(f"seq{i:02d}", role, float(dur), plan, ft, kt, srng))

    def job_for(seq: _Sequence | None) -> SimJob:
        if seq is None:
            pt, pc, ot = np.array([0.0]), np.array([[size[0] / 2, size[1] / 2, size[2] + 0.05]]), np.array([0.0])
        else:
            pt = np.linspace(0.0, seq.duration, int(np.ceil(seq.duration * 200)) + 1)
            pc, ot = seq.plan.trajectory(pt), seq.frame_times
        return SimJob(mesh_spec, phantom.mass, E, cfg.poisson_ratio, cfg.law, float(cfg.stiffening),
                      float(cfg.contact_stiffness_per_modulus), cfg.dt, cfg.newton_iterations,
                      cfg.rayleigh_mass, cfg.rayleigh_stiffness, physical, pt, pc, r_true, ot)

    if phantom.stl_path is None:
        mesh_spec = ("grid", tuple(cfg.grid), tuple(float(v) for v in PHANTOM_SIZE))
    else:
        from core.simulation.meshing import default_element_size

        volume = phantom.mass / PHANTOM_DENSITY
        mesh_spec = ("stl", str(phantom.stl_path), default_element_size(volume, int(np.prod(cfg.grid))))
    try:
        mesh = truth_mesh(mesh_spec)
    except TissueTwinError as exc:
        shutil.rmtree(workdir, ignore_errors=True)
        raise LabError(f"the phantom cannot be meshed: {exc}") from exc
    triangles = np.asarray(mesh.surface_triangles)

    meta = SessionMeta(
        phantom=PhantomSpec(size=size, mass=phantom.mass, fixed="bottom"),
        probe=ProbeSpec(radius=r_nominal),
        camera=CameraSpec(rate_hz=float(cfg.camera_rate_hz), depth_accuracy=float(cfg.depth_accuracy),
                          intrinsics=intrinsics.to_dict()),
        sequences=tuple(SequenceSpec(s.name, s.role) for s in sequences),
        raw={},
        **({"landmarks": phantom.landmarks} if phantom.landmarks else {}),
    )
    total_frames = sum(len(s.frame_times) for s in sequences)
    sim_share = 0.5  # rough split of the progress bar between simulation and rendering
    done_frames = 0

    executor = None
    if cfg.workers > 0:
        import multiprocessing

        # "spawn": the parent holds Open3D/TBB threads, which fork() does not copy safely
        executor = ProcessPoolExecutor(max_workers=cfg.workers, mp_context=multiprocessing.get_context("spawn"))
    try:
        with SessionWriter(out, meta, overwrite=overwrite) as writer:
            report(0.0, "calibration")
            write_calibration(writer, phantom, cfg, r_true, T_robot_phantom, corner_rng)

            # ---- reference cloud: the phantom at rest, no instrument, averaged frames
            rest = rest_positions(job_for(None))
            writer.write_reference(rig.reference_points(rest, triangles, cfg.reference_frames, reference_rng))

            # ---- sequences: simulate ahead in workers, render and write in order
            futures: dict[int, Future] = {}

            def submit(k: int) -> None:
                if executor is not None and k < len(sequences) and k not in futures:
                    futures[k] = executor.submit(run_sim, job_for(sequences[k]))

            for k in range(cfg.workers):
                submit(k)
            seq_meta = []
            retried: dict[str, dict] = {}
            for i, seq in enumerate(sequences):
                base = done_frames / total_frames
                span = len(seq.frame_times) / total_frames
                report(base, f"{seq.name}: truth simulation")
                sim_out = None
                if executor is not None:
                    try:
                        submit(i)
                        sim_out = futures.pop(i).result()
                        submit(i + cfg.workers)
                    except BrokenProcessPool:
                        # e.g. a script without an ``if __name__ == "__main__"`` guard: the
                        # spawned worker cannot start. Same results, just without overlap.
                        executor.shutdown(wait=False, cancel_futures=True)
                        executor = None
                        futures.clear()
                        report(base, "worker process failed to start; simulating in-process")
                if sim_out is not None:
                    positions, force, status, message, sim_wall = sim_out
                else:
                    def sim_cb(fr, msg, _b=base, _s=span, _n=seq.name):
                        report(_b + _s * sim_share * fr, f"{_n}: truth simulation")
                    positions, force, status, message, sim_wall = run_sim(job_for(seq), sim_cb)
                if status != "ok":
                    # a stiff contact on a fine mesh can outrun one Newton iteration per
                    # step (field seed 111: 31x11x11, 1.4e6 E/m, diverged at 2.9 s):
                    # retry with the stronger numerics of TRUTH_RETRIES, as a careful lab
                    # would, and record what it took in truth.json
                    for newton, dt_div in TRUTH_RETRIES:
                        job = replace(job_for(seq), newton_iterations=max(newton, cfg.newton_iterations),
                                      dt=cfg.dt / dt_div)
                        report(base, f"{seq.name}: truth diverged ({message}); retrying with {job.newton_iterations} "
                                     f"Newton iterations, dt {job.dt:.3g} s")
                        positions, force, status, message, sim_wall = run_sim(job)
                        if status == "ok":
                            retried[seq.name] = {"newton_iterations": job.newton_iterations, "dt": job.dt}
                            break
                if status != "ok":
                    raise LabError(f"truth simulation of {seq.name} (seed {seed}) {status}: {message}")

                # kinematics as the robot reports them
                srng = seq.rng
                writer.write_kinematics(seq.name, recorded_kinematics(
                    seq.plan, seq.kin_t, seq.frame_times, force, cfg, with_force=with_force, time_offset=time_offset,
                    kin_offset=kin_offset, T_robot_phantom=T_robot_phantom, srng=srng))

                # depth frames
                centres = seq.plan.trajectory(seq.frame_times)
                shaft = seq.plan.shaft_direction
                n_f = len(seq.frame_times)
                every = max(n_f // 20, 1)
                max_disp = 0.0
                for f, t in enumerate(seq.frame_times):
                    max_disp = max(max_disp, float(np.linalg.norm(positions[f] - mesh.nodes, axis=1).max()))
                    inst = Instrument(centre=centres[f], shaft_direction=shaft, radius=r_true)
                    pts = rig.frame_points(positions[f], triangles, inst, srng)
                    writer.write_frame(seq.name, f, float(t), pts)
                    if f % every == 0:
                        report(base + span * (sim_share + (1 - sim_share) * f / n_f)
                               if executor is None else base + span * f / n_f,
                               f"{seq.name}: frame {f + 1}/{n_f}")
                done_frames += n_f
                seq_meta.append({
                    "name": seq.name, "role": seq.role, "duration": seq.duration,
                    "n_frames": n_f,
                    "tool_quaternion_phantom": quat_xyzw(seq.plan.R_phantom_tool).tolist(),
                    "pokes": [p.to_dict() for p in seq.plan.pokes],
                    "max_contact_force": float(np.max(np.linalg.norm(force, axis=1))),
                    "max_displacement": max_disp,
                })
                del positions

            truth = {
                "format": "tissue-truth/1",
                "generator": {"name": GENERATOR_NAME, "version": GENERATOR_VERSION, "preset": preset_name,
                              "seed": int(seed)},
                "T_phantom_robot": T_phantom_robot.tolist(),
                "T_phantom_camera": T_phantom_camera.tolist(),
                "youngs_modulus": E,
                "poisson_ratio": float(cfg.poisson_ratio),
                "material": material_truth(cfg, size),
                "effects": full_effects,
                "probe": {"radius_nominal": r_nominal, "radius_true": r_true,
                          "shaft_radius": Instrument.shaft_radius, "shaft_length": Instrument.shaft_length},
                "camera": {**intrinsics.to_dict(), "roi": list(rig.roi), "rate_hz": cfg.camera_rate_hz,
                           "noise": asdict(cfg.depth_noise), "table_z": float(rig.table[0][0, 2]),
                           "table_margin": cfg.table_margin},
                "kinematics": {"rate_hz": cfg.kinematics_rate_hz, "encoder_noise": cfg.encoder_noise,
                               "force": bool(with_force), "force_noise": cfg.force_noise if with_force else None,
                               "corner_noise": cfg.corner_noise},
                "mesh": ({"grid": list(cfg.grid), "nodes": int(mesh.n_nodes), "tets": int(mesh.n_tets),
                          "split": "6 tets per hex (Kuhn)"} if mesh_spec[0] == "grid" else
                         {"shape": phantom.shape, "mesher": "gmsh", "element_size": float(mesh_spec[2]),
                          "nodes": int(mesh.n_nodes), "tets": int(mesh.n_tets)}),
                "sim": {"dt": cfg.dt, "integrator": "implicit_euler", "newton_iterations": cfg.newton_iterations},
                "sequences": seq_meta,
            }
            # keys added only when used, so that sessions of older configs stay byte-identical
            if cfg.contact_stiffness_per_modulus != 2e5:
                truth["sim"]["contact_stiffness_per_modulus"] = float(cfg.contact_stiffness_per_modulus)
            if retried:
                truth["sim"]["retried"] = retried
            if drawn is not None:
                truth["lab_variation"] = {**drawn, "depth_noise_sigma": float(cfg.depth_noise.sigma),
                                          "ranges": cfg.variation.to_dict()}
            writer.write_truth(truth)
            path = writer.finish()
    finally:
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)
        MODEL_CACHE.clear()
        shutil.rmtree(workdir, ignore_errors=True)
    report(1.0, f"done in {time.perf_counter() - t_wall:.1f} s")
    return path
