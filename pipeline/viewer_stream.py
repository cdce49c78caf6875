"""One Rerun recording of a run and the entities the viewer draws, for the live viewer
(:mod:`lrslam.pipeline.viewer`) and the replay of a run folder (:mod:`lrslam.pipeline.viewer_replay`).

rerun-sdk is optional (``pip install 'lrslam[viewer]'``) and imported when a stream opens. Each
:class:`RerunStream` owns its own ``rerun.RecordingStream`` (no global recording): it spawns a viewer, records to
an ``.rrd`` file, or both, and is flushed and closed by :meth:`RerunStream.close` (also on Ctrl-C when used as a
context manager).

Entities (world frame = the run's world, metres; cameras OpenCV: x right, y down, z forward):

- ``world/camera``: the tracked pose ``T_w_c`` (Transform3D), one per frame; ``world/camera/image``: its
  Pinhole (the frustum) with ``rgb`` (Image) and ``depth`` (DepthImage, metres); ``world/camera/render``: the
  field rendered at the pose (its own Pinhole, smaller) with ``depth`` and ``rgb``;
- ``world/trajectory/{fused,seed,frontend,gt}`` (LineStrips3D): the run's trajectory, the per-frame seeds, the
  frontend's own estimate, the ground truth (aligned to the run's world as the ATE aligns);
- ``world/keyframes`` (Points3D), ``world/loops`` (LineStrips3D between the keyframes of each loop),
  ``world/corrections`` (Arrows3D: each keyframe the pose graph moved, from its old to its new position),
  ``world/mesh`` (Mesh3D);
- time series: ``metrics/ate_cm``, ``metrics/graph_shift_cm``, ``timings/<stage>_s``; ``run/summary`` (text).

Time lines: ``frame`` (0-based index) and ``time`` (the frame's timestamp, seconds; shown as a date when it is
a Unix time).
"""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np

from lrslam.errors import InputError

__all__ = ["RerunStream", "import_rerun", "MISSING_RERUN", "COLOURS"]

MISSING_RERUN = "the viewer needs rerun-sdk: pip install 'lrslam[viewer]'"
COLOURS = {"fused": (40, 200, 90), "seed": (240, 150, 40), "frontend": (70, 140, 255), "gt": (220, 220, 220),
           "loops": (255, 60, 200), "corrections": (255, 60, 60), "keyframes": (255, 220, 0), "camera": (40, 200, 90)}
_UNIX_TIME = 1e9   # a timestamp above this (2001-09-09) is a Unix time, else seconds from the sequence's start


def import_rerun():
    """The ``rerun`` module; InputError with :data:`MISSING_RERUN` when rerun-sdk is not installed."""
    try:
        import rerun
    except ImportError:
        raise InputError(MISSING_RERUN) from None
    return rerun


class RerunStream:
    """A Rerun recording: ``spawn`` a viewer (streamed to it live) and / or record to ``rrd`` (an ``.rrd`` file,
    its folder created). InputError when rerun-sdk is missing or neither is asked for."""

    def __init__(self, spawn: bool = False, rrd: str | Path | None = None, name: str = "lrslam") -> None:
        if not spawn and rrd is None:
            raise InputError("the viewer needs somewhere to go: spawn a viewer or give an .rrd file")
        self.rr = rr = import_rerun()
        self.rec = rr.RecordingStream("lrslam", recording_id=str(uuid.uuid4()))
        sinks = []
        if spawn:
            self.rec.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        if rrd is not None:
            Path(rrd).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(rrd)))
        self.rec.set_sinks(*sinks)
        self.rec.send_recording_name(name)
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self._closed = False

    # ------------------------------------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Flush everything logged and close the file / connection (idempotent)."""
        if not self._closed:
            self._closed = True
            self.rec.flush()
            self.rec.disconnect()

    def __enter__(self) -> RerunStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------------ time
    def at(self, index: int, timestamp: float) -> None:
        """Log what follows at frame ``index`` (0-based) and time ``timestamp`` (s)."""
        self.rec.set_time("frame", sequence=int(index))
        if timestamp > _UNIX_TIME:
            self.rec.set_time("time", timestamp=float(timestamp))
        else:
            self.rec.set_time("time", duration=float(timestamp))

    # ------------------------------------------------------------------------------------------------ entities
    def camera(self, T_w_c: np.ndarray) -> None:
        """``world/camera`` at ``T_w_c`` (4, 4)."""
        T = np.asarray(T_w_c, dtype=np.float64)
        self.rec.log("world/camera", self.rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))

    def pinhole(self, entity: str, K: np.ndarray, width: int, height: int, plane_m: float = 0.15) -> None:
        """A static Pinhole (intrinsics ``K`` (3, 3) of ``width`` x ``height`` images; frustum ``plane_m`` deep)."""
        rr = self.rr
        self.rec.log(entity, rr.Pinhole(image_from_camera=np.asarray(K, dtype=np.float64), resolution=[width, height],
                                        camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=plane_m,
                                        color=COLOURS["camera"]), static=True)

    def images(self, entity: str, rgb: np.ndarray | None, depth: np.ndarray | None) -> None:
        """``<entity>/rgb`` (H, W, 3) uint8 or float in [0, 1] and ``<entity>/depth`` (H, W) metres (0 = none)."""
        rr = self.rr
        if rgb is not None:
            if rgb.dtype != np.uint8:
                rgb = (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
            self.rec.log(f"{entity}/rgb", rr.Image(rgb))
        if depth is not None:
            self.rec.log(f"{entity}/depth", rr.DepthImage(np.asarray(depth, dtype=np.float32), meter=1.0))

    def trajectory(self, name: str, positions: np.ndarray, static: bool = False) -> None:
        """``world/trajectory/<name>``: one line through ``positions`` (N, 3) metres (nothing below 2 points)."""
        p = np.asarray(positions, dtype=np.float32)
        if len(p) >= 2:
            self.rec.log(f"world/trajectory/{name}", self.rr.LineStrips3D([p], colors=[COLOURS[name]], radii=[0.004]),
                         static=static)

    def keyframes(self, positions: np.ndarray, ids: list[int] | tuple[int, ...], static: bool = False) -> None:
        """``world/keyframes``: points (K, 3) metres labelled by frame index."""
        self.rec.log("world/keyframes", self.rr.Points3D(np.asarray(positions, dtype=np.float32),
                                                         colors=[COLOURS["keyframes"]], radii=[0.012],
                                                         labels=[str(i) for i in ids], show_labels=False),
                     static=static)

    def loops(self, segments: np.ndarray) -> None:
        """``world/loops``: one segment (2, 3) metres per loop closure, (L, 2, 3)."""
        if len(segments):
            self.rec.log("world/loops", self.rr.LineStrips3D(np.asarray(segments, dtype=np.float32),
                                                             colors=[COLOURS["loops"]], radii=[0.006]))

    def corrections(self, before: np.ndarray, after: np.ndarray, shift_cm: float) -> None:
        """``world/corrections``: arrows from each moved keyframe's old position (K, 3) to its new one (K, 3),
        and ``metrics/graph_shift_cm``: the largest shift."""
        b = np.asarray(before, dtype=np.float32)
        self.rec.log("world/corrections", self.rr.Arrows3D(origins=b, vectors=np.asarray(after, np.float32) - b,
                                                           colors=[COLOURS["corrections"]]))
        self.scalar("metrics/graph_shift_cm", shift_cm)

    def mesh(self, mesh, static: bool = False) -> bool:
        """``world/mesh`` from a ``trimesh.Trimesh`` (world metres, vertex colours when it has them); False when
        the mesh is empty (nothing logged)."""
        if mesh is None or len(mesh.faces) == 0:
            return False
        colours = None
        if mesh.visual.kind == "vertex":   # trimesh: the mesh has per-vertex colours
            colours = np.asarray(mesh.visual.vertex_colors)[:, :3]
        self.rec.log("world/mesh", self.rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
                                                  triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
                                                  vertex_colors=colours), static=static)
        return True

    def scalar(self, entity: str, value: float) -> None:
        """One sample of the time series ``entity`` (non-finite values are skipped)."""
        if value is not None and np.isfinite(value):
            self.rec.log(entity, self.rr.Scalars(float(value)))

    def text(self, entity: str, markdown: str) -> None:
        """A static markdown document (the run's summary, its metrics)."""
        self.rec.log(entity, self.rr.TextDocument(markdown, media_type=self.rr.MediaType.MARKDOWN), static=True)
