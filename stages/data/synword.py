"""The synthetic WORD-style generator (``data=synword``): scenes -> four fisheye renders -> labels.

Labels come from the render: a box is the bbox of the object's visible pixels in the id buffer (a
vehicle's includes its visible wheels), an object is annotated only if at least ``min_visible_fraction``
of the pixels it would cover unoccluded are visible and its shorter side is at least ``min_box_px``; every
other object with a visible pixel becomes an ignore region (``Record.ignore``): the bbox it would cover unoccluded;
relations, roles and couples come from the 3D truth. Frames are independent (per-frame seed from the
config seed and the frame index), so generation parallelises across processes and stays deterministic.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from deepword.cameras import ego_body_outline
from deepword.progress import progress_lines
from deepword.word_format import CAMERAS, VEHICLE, WHEEL, Record
from stages.data.backdrop import GroundBank, cloud_field, draw_look, ground_texture
from stages.data.camera import rig_cameras
from stages.data.domain import DomainConfig
from stages.data.render import build_tables, ego_vehicle, render_camera
from stages.data.sensor import apply_sensor, draw_sensor, noise_bank
from stages.data.world import SceneSampler


class FrameGenerator:
    """Everything a process needs to render frames; a rig's per-camera tables are built once per process."""

    def __init__(self, cfg: dict, seed: int):
        self.cfg = cfg
        self.seed = int(seed)
        self.ego = ego_vehicle(cfg["ego"])
        # calibrations and 3D truth are written in ISO 8855's vehicle frame: origin under the rear axle
        self.rear_axle = np.array([self.ego.wheels[0][2][0], 0.0, 0.0])
        self._rig: tuple[int, list] | None = None  # (rig index, its cameras' tables): rigs change rarely
        self.stream = int(cfg.get("stream", 0))
        self.domain = DomainConfig.from_cfg(cfg.get("domain"))
        self.sampler = SceneSampler(cfg["scenes"], self.domain, self.ego.length, self.ego.width)
        self.grounds = GroundBank(self.domain.grounds)
        self.clouds = cloud_field()
        w, h = max_image_size(cfg)
        self.sensor_noise = noise_bank(w, h)

    def tables(self, frame_id: int) -> list:
        """The per-pixel tables of the frame's rig (``data.lens.frames_per_rig`` consecutive frames share
        one rig: building a rig's tables costs about as much as rendering a frame)."""
        rig = int(frame_id) // int(self.cfg["lens"]["frames_per_rig"])
        if self._rig is None or self._rig[0] != rig:
            tables = [build_tables(cam, self.ego) for cam in rig_cameras(self.cfg, self.seed, rig, CAMERAS)]
            for t in tables:   # the calibration says where the ego's body covers the image, as a rig's would
                t.cam = replace(t.cam, ego_body=tuple(tuple(map(tuple, p)) for p in ego_body_outline(t.ego_mask)))
            self._rig = (rig, tables)
        return self._rig[1]

    def frame_rng(self, frame_id: int) -> np.random.Generator:
        """The frame's own random stream: a pure function of the seed, the dataset's stream (the held-out
        dataset draws other scenes than the in-domain one) and the frame index."""
        return np.random.default_rng(np.random.SeedSequence([self.seed, self.stream, int(frame_id)]))

    def render_frame(self, frame_id: int):
        """-> list of (camera name, RGB uint8 image, Record) for the frame's four cameras."""
        rng = self.frame_rng(frame_id)
        scene = self.sampler.sample(rng)
        d = self.domain
        look = draw_look(rng, d.draw(rng, "skies"), d.draw(rng, "grounds"), d.sun_elevation_deg)
        tex = ground_texture(self.grounds, look, scene)
        frame_domain = look.to_record() | scene_families(scene)
        out = []
        for tables in self.tables(frame_id):
            rgb, _, vstats, wstats = render_camera(tables, scene, tex, look, self.clouds)
            sensor = draw_sensor(rng, d.sensor)
            img = apply_sensor(rgb, sensor, rng, self.sensor_noise, tables.falloff)
            rec = self.labels(frame_id, tables.cam, scene, vstats, wstats, rng)
            rec.extra["domain"] = frame_domain | {"sensor": sensor.to_record()}
            out.append((tables.cam.name, img, rec))
        return out

    def labels(self, frame_id, cam, scene, vstats, wstats, rng) -> Record:
        min_vis, min_px = self.cfg["min_visible_fraction"], self.cfg["min_box_px"]

        def annotated(st) -> bool:
            if st.bbox is None or st.own_px == 0:
                return False
            x1, y1, x2, y2 = st.bbox
            return st.visible_px / st.own_px >= min_vis and min(x2 - x1, y2 - y1) >= min_px

        nv = len(scene.vehicles)
        objs = [(VEHICLE, i) for i in range(nv) if annotated(vstats[i])]
        objs += [(WHEEL, j) for j in range(4 * nv) if annotated(wstats[j])]
        ids = rng.permutation(len(objs))  # box ids carry no hint of which wheel belongs to which vehicle
        box_id = {obj: int(b) for obj, b in zip(objs, ids, strict=True)}
        boxes = []
        for (cls, idx), b in zip(objs, ids, strict=True):
            st = vstats[idx] if cls == VEHICLE else wstats[idx]
            boxes.append([*map(float, st.bbox), 1.0, cls, int(b)])
        relations, pairs = [], []
        for i, v in enumerate(scene.vehicles):
            for k, (role, _, _) in enumerate(v.wheels):
                wk = (WHEEL, 4 * i + k)
                if wk in box_id and (VEHICLE, i) in box_id:
                    relations.append((box_id[(VEHICLE, i)], box_id[wk], role))
            for rear, front in ((0, 1), (2, 3)):  # wheels are listed rear, front per side
                a, b = (WHEEL, 4 * i + rear), (WHEEL, 4 * i + front)
                if a in box_id and b in box_id:
                    pairs.append((box_id[a], box_id[b]))
        arr = np.array(sorted(boxes, key=lambda r: r[6]), dtype=np.float64).reshape(-1, 7)
        # what is visible but too hidden (or too small) to label: ignore regions where it would be seen unoccluded
        # (a detector boxes a half-hidden wheel whole), so that a detector that finds it and a relation model that
        # claims it are not counted wrong. Drawn after the ids: the labels stay as they were.
        hidden = [(cls, st.bbox if st.own_bbox is None else st.own_bbox)
                  for cls, stats in ((VEHICLE, vstats), (WHEEL, wstats))
                  for k, st in enumerate(stats) if (cls, k) not in box_id and st.bbox is not None and st.visible_px]
        ignore = np.array([[*map(float, box), cls] for cls, box in hidden], dtype=np.float64).reshape(-1, 5)
        extra = {"layout": scene.layout, "calibration": cam.shifted(self.rear_axle).calibration(),
                 "objects_3d": self.objects_3d(scene, box_id)}
        return Record(image=image_path(cam.name, frame_id), frame_id=int(frame_id), camera=cam.name,
                      width=int(cam.width), height=int(cam.height), boxes=arr, relations=relations,
                      wheel_pairs=pairs, scene=scene.kind, extra=extra, ignore=ignore)

    def objects_3d(self, scene, box_id: dict) -> dict:
        """3D truth of the annotated objects in the ISO 8855 vehicle frame (docs/design.md §4): vehicles as boxes,
        wheels by their ground contact point (the middle of the tyre's footprint)."""
        out = {}
        for (cls, idx), bid in sorted(box_id.items(), key=lambda kv: kv[1]):
            if cls == VEHICLE:
                v = scene.vehicles[idx]
                centre = v.to_ego(np.array([0.0, 0.0, v.height / 2])) - self.rear_axle
                out[str(bid)] = {"center": [round(float(c), 4) for c in centre],
                                 "size": [round(float(v.length), 4), round(float(v.width), 4), round(float(v.height), 4)],
                                 "yaw": round(float(math.remainder(v.yaw, 2 * math.pi)), 5)}
            else:
                v = scene.vehicles[idx // 4]
                _, _, (x, y) = v.wheels[idx % 4]
                contact = v.to_ego(np.array([x, y, 0.0])) - self.rear_axle
                out[str(bid)] = {"contact": [round(float(contact[0]), 4), round(float(contact[1]), 4)]}
        return out


def max_image_size(cfg: dict) -> tuple[int, int]:
    """The largest image a rig of this config can have (the sensor-noise bank covers every size)."""
    w, h = cfg["image_size"]
    lens = cfg["lens"]
    if not lens["randomise"]:
        return int(w), int(h)
    widest = 2 * round(w * max(lens["width_scales"]) / 2)
    return widest, 2 * round(widest / min(lens["image_aspects"]) / 2)


def scene_families(scene) -> dict:
    """The families a frame's scene drew on each object axis (recorded per image, checked by the tests that
    keep held-out families out of training data)."""
    vs = scene.vehicles
    return {"bodies": sorted({v.kind for v in vs}), "paints": sorted({v.paint for v in vs}),
            "materials": sorted({v.material for v in vs}), "wheels": sorted({v.wheel_look.style for v in vs}),
            "props": sorted({p.kind for p in scene.props})}


def image_path(camera: str, frame_id: int) -> str:
    return f"images/{camera}/{frame_id:06d}.png"


# --- parallel generation ------------------------------------------------------------------------------

_WORKER: dict = {}


def _init_worker(cfg: dict, seed: int, out_dir: str) -> None:
    from threadpoolctl import threadpool_limits

    # one process per core: OpenCV's and OpenBLAS's own threads would oversubscribe. OpenBLAS's took a rendering
    # process to ~1.45 cores for no gain in its speed, so two processes on 2 cores rendered 1.2x as fast as one
    cv2.setNumThreads(1)
    _WORKER["blas"] = threadpool_limits(limits=1, user_api="blas")   # held for the process's life
    _WORKER["gen"] = FrameGenerator(cfg, seed)
    _WORKER["out"] = Path(out_dir)


def _work(frame_id: int) -> list[Record]:
    return write_frame(_WORKER["gen"], frame_id, _WORKER["out"])


PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1]   # the generator's PNGs: the fastest level that compresses (writing is 14 % of a frame)


def renderer_processes(workers: int | None, frames: int | None = None) -> int:
    """The processes that render: ``workers`` (None: one per core), no more than ``frames``, at least one."""
    return max(1, min(int(workers or os.cpu_count() or 1), frames or 1 << 30))


def write_frame(gen: FrameGenerator, frame_id: int, out_dir: Path) -> list[Record]:
    """Render a frame, write its images, return the records worth keeping (>= 1 owner-member relation)."""
    kept = []
    for _, img, rec in gen.render_frame(frame_id):
        if not rec.relations:
            continue
        path = out_dir / rec.image
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), PNG_PARAMS)
        kept.append(rec)
    return kept


def generate(cfg: dict, seed: int, out_dir: Path, workers: int | None = None, progress: bool = True) -> list[Record]:
    """Generate ``cfg['frames']`` frames into ``out_dir`` (images/<camera>/<frame>.png); returns the records
    in frame, camera order. ``workers`` processes (default: all cores); 1 renders in this process."""
    n = int(cfg["frames"])
    with FrameWriter(cfg, seed, out_dir, workers, most=n) as writer:
        results = writer.write(range(n), progress=progress)
    return [r for recs in results for r in recs]


class FrameWriter:
    """Renders and writes chosen frames of one config, in this process or a pool of ``workers`` processes kept
    for the writer's life (the data stage's pool source asks for frames in several batches). ``write`` returns
    each frame's kept records (>= 1 owner-member relation), in camera order, in the order the frames were asked for."""

    def __init__(self, cfg: dict, seed: int, out_dir: Path, workers: int | None = None, most: int | None = None):
        DomainConfig.from_cfg(cfg.get("domain"))  # a bad config fails here, not in a pool initializer (which would hang)
        self.cfg, self.seed, self.out_dir = cfg, int(seed), Path(out_dir)
        self.workers = renderer_processes(workers, most)
        self._gen: FrameGenerator | None = None
        self._pool = None

    def __enter__(self) -> FrameWriter:
        if self.workers == 1:
            self._gen = FrameGenerator(self.cfg, self.seed)
        else:
            ctx = mp.get_context("spawn")  # safe whatever threads the parent runs (MLflow, torch)
            self._pool = ctx.Pool(self.workers, initializer=_init_worker,
                                  initargs=(self.cfg, self.seed, str(self.out_dir)))
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.terminate() if exc[0] is not None else self._pool.close()
            self._pool.join()

    def write(self, frames, progress: bool = True) -> list[list[Record]]:
        frames = [int(f) for f in frames]

        def shown(items):
            return progress_lines(items, total=len(frames), desc="synword frames", unit="frame") if progress else items

        if self._gen is not None:
            results = [write_frame(self._gen, f, self.out_dir) for f in shown(frames)]
        else:
            # a chunk of one rig's frames: each process builds a rig's tables once
            chunk = max(1, int(self.cfg["lens"]["frames_per_rig"]))
            results = list(shown(self._pool.imap(_work, frames, chunksize=chunk)))
        order = {c: i for i, c in enumerate(CAMERAS)}
        return [sorted(recs, key=lambda r: order[r.camera]) for recs in results]
