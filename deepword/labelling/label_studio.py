"""Label Studio: its JSON export (a list of tasks) in, and tasks with pre-annotations (``predictions``) out.

Read from each task: ``data`` (the image under the key ``image``, else the first value naming a PNG/JPEG;
optional ``camera``, ``frame_id``, ``scene``), and from one annotation (the latest one not cancelled, by
``updated_at``/``created_at``) its ``result``: ``rectanglelabels`` regions (``value.x/y/width/height`` in percent
of ``original_width``/``original_height``, one label: ``vehicle`` or ``wheel``) and ``relation`` results
(``from_id``, ``to_id``, ``labels``): wheel <-> vehicle labelled ``front``/``rear`` (or unlabelled) is ownership;
wheel -> wheel labelled ``couple`` (or unlabelled) a couple, drawn from the rear to the front wheel.
The labelling configuration that produces exactly this ships as ``label_studio.xml``.
"""

from __future__ import annotations

import json
from pathlib import Path

from deepword.labelling.build import (
    COUPLE,
    IMAGE_SUFFIXES,
    LABEL_OF_CLASS,
    RawBox,
    RawImage,
    RawLink,
    explicit_pairs,
    to_number,
)
from deepword.labelling.problems import LabellingError, Problems
from deepword.word_format import Record

CONFIG_FILE = Path(__file__).with_name("label_studio.xml")
FROM_NAME, TO_NAME = "label", "image"  # the config's RectangleLabels and Image names


def config() -> str:
    """The shipped labelling configuration (paste it into the project's Labeling Interface > Code)."""
    return CONFIG_FILE.read_text()


def load_json(path: Path):
    try:
        return json.loads(Path(path).read_text(encoding="utf-8-sig"))
    except OSError as exc:
        raise LabellingError(f"{path}: cannot be read: {exc.strerror}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise LabellingError(f"{path}: not a JSON file: {exc}") from None


def _image_ref(data: dict) -> tuple[str | None, str]:
    if isinstance(data.get("image"), str):
        return data["image"], "data.image"
    for key, value in data.items():
        if isinstance(value, str) and value.lower().split("?")[0].endswith(IMAGE_SUFFIXES):
            return value, f"data.{key}"
    return None, "data.image"


def _choose(annotations: list, where: str, problems: Problems) -> tuple[dict | None, int]:
    """The latest annotation not cancelled (ties: the later in the list), and how many the task has."""
    if not isinstance(annotations, list):
        problems.add(where, "annotations", "must be a list")
        return None, 0
    live = [(i, a) for i, a in enumerate(annotations) if isinstance(a, dict) and not a.get("was_cancelled")]
    if not live:
        return None, 0
    _, best = max(live, key=lambda ia: (str(ia[1].get("updated_at") or ia[1].get("created_at") or ""), ia[0]))
    return best, len(annotations)


def read_label_studio(path: Path, problems: Problems) -> tuple[list[RawImage], list[str]]:
    """Every annotated task of a Label Studio JSON export as a RawImage, and notes for the summary."""
    tasks = load_json(path)
    if isinstance(tasks, dict) and "data" in tasks:
        tasks = [tasks]
    if not isinstance(tasks, list):
        raise LabellingError(f"{path}: a Label Studio JSON export is a list of tasks, got {type(tasks).__name__}")
    images: list[RawImage] = []
    unannotated, several = [], []
    for t, task in enumerate(tasks):
        if not isinstance(task, dict):
            problems.add(f"task #{t + 1}", "<task>", f"expected a JSON object, got {type(task).__name__}")
            continue
        tid = task.get("id", f"#{t + 1}")
        where = f"task {tid}"
        data = task.get("data")
        if not isinstance(data, dict):
            problems.add(where, "data", "missing (the task's image)")
            continue
        ref, ref_field = _image_ref(data)
        if ref is None:
            problems.add(where, "data.image", "no image in the task's data")
            continue
        annotation, n_annotations = _choose(task.get("annotations", []), where, problems)
        if annotation is None:
            unannotated.append(str(tid))
            continue
        if n_annotations > 1:
            several.append(f"{tid} (annotation {annotation.get('id', '?')})")
        img = RawImage(where=where, name=ref, name_field=ref_field, size_fields=("original_width", "original_height"),
                       camera=data.get("camera"), scene=str(data.get("scene", "")))
        if "frame_id" in data:
            fid = to_number(data["frame_id"], where, "data.frame_id", problems)
            if fid is not None and not fid.is_integer():
                problems.add(where, "data.frame_id", f"must be an integer, got {data['frame_id']!r}")
            img.frame_id = int(fid) if fid is not None and fid.is_integer() else None
        results = annotation.get("result", [])
        if not isinstance(results, list):
            problems.add(where, "annotations.result", "must be a list")
            continue
        _read_results(img, results, problems)
        images.append(img)
    notes = []
    if unannotated:
        notes.append(f"{len(unannotated)} tasks without an annotation (none, or all cancelled) were not imported: "
                     f"task {', '.join(unannotated[:10])}{' ...' if len(unannotated) > 10 else ''}")
    if several:
        notes.append(f"{len(several)} tasks have several annotations; took the latest one not cancelled: "
                     f"task {', '.join(several[:10])}{' ...' if len(several) > 10 else ''}")
    else:
        notes.append("one annotation per task (cancelled ones are skipped)")
    return images, notes


def _read_results(img: RawImage, results: list, problems: Problems) -> None:
    for k, res in enumerate(results):
        if not isinstance(res, dict):
            problems.add(img.where, f"result[{k}]", "expected a JSON object")
            continue
        kind = res.get("type")
        if kind == "rectanglelabels":
            _region(img, res, k, problems)
        elif kind == "relation":
            ends = f"relation {res.get('from_id')!r} -> {res.get('to_id')!r}"
            where = f"{img.where}, {ends}"
            labels = res.get("labels") or []
            if not isinstance(labels, list) or len(labels) > 1:
                problems.add(where, "labels", f"expected at most one label, got {labels!r}")
                continue
            if res.get("from_id") is None or res.get("to_id") is None:
                problems.add(where, "from_id" if res.get("from_id") is None else "to_id", "missing")
                continue
            label = str(labels[0]).strip().lower() if labels else None
            a, b = str(res["from_id"]), str(res["to_id"])
            if res.get("direction") == "left":  # drawn the other way round
                a, b = b, a
            img.links.append(RawLink(a, b, label, where, "to_id"))
        else:
            problems.add(f"{img.where}, result {res.get('id', k)!r}", "type",
                         f"unsupported result type {kind!r} (rectanglelabels and relation only)")


def _region(img: RawImage, res: dict, k: int, problems: Problems) -> None:
    rid = res.get("id")
    where = f"{img.where}, region {rid!r}" if rid is not None else f"{img.where}, result[{k}]"
    if rid is None:
        problems.add(where, "id", "missing (relations name regions by id)")
        return
    for fld in ("original_width", "original_height"):
        if fld in res:
            value = to_number(res[fld], where, fld, problems)
            if value is None:
                return
            have = img.width if fld == "original_width" else img.height
            if have is not None and have != int(value):
                problems.add(where, fld, f"{int(value)} differs from {have} in an earlier region of the task")
                return
            if fld == "original_width":
                img.width = int(value)
            else:
                img.height = int(value)
    value = res.get("value")
    if not isinstance(value, dict):
        problems.add(where, "value", "missing")
        return
    labels = value.get("rectanglelabels")
    if not isinstance(labels, list) or len(labels) != 1:
        problems.add(where, "value.rectanglelabels", f"expected exactly one label, got {labels!r}")
        return
    fields = ("value.x", "value.y", "value.width", "value.height")
    nums = [to_number(value.get(f.split(".")[1]), where, f, problems) for f in fields]
    if any(n is None for n in nums):
        return
    rotation = to_number(value.get("rotation", 0) or 0, where, "value.rotation", problems)
    if rotation is None:
        return
    if abs((rotation + 180) % 360 - 180) > 0.01:
        problems.add(where, "value.rotation", f"rotated boxes are not supported (rotation {rotation}); "
                                              f"the format has axis-aligned boxes")
        return
    score = res.get("score", 1.0)
    img.boxes.append(RawBox(key=str(rid), where=where, label=labels[0], label_field="value.rectanglelabels",
                            coords=tuple(nums), coord_fields=fields, percent=True,
                            score=float(score) if isinstance(score, (int, float)) else 1.0))


def image_url(image: str, image_root: str | None) -> str:
    """The task's image reference: ``image_root`` (a URL or path prefix) joined to the record's relative path."""
    if not image_root:
        return image
    return image_root + image if image_root.endswith(("/", "=")) else f"{image_root}/{image}"


def to_label_studio(records: list[Record], model_version: str = "deepword", image_root: str | None = None,
                    ) -> tuple[list[dict], list[str]]:
    """Tasks whose ``predictions`` hold the records' boxes (with scores) and relations, for a team to correct in
    Label Studio, and notes on what the format cannot carry."""
    tasks, lost = [], 0
    for rec in records:
        w, h = rec.width, rec.height
        result: list[dict] = []
        for x1, y1, x2, y2, score, cls, bid in rec.boxes:
            result.append({
                "id": str(int(bid)), "type": "rectanglelabels", "from_name": FROM_NAME, "to_name": TO_NAME,
                "original_width": w, "original_height": h, "image_rotation": 0, "score": round(float(score), 4),
                "value": {"x": x1 / w * 100, "y": y1 / h * 100, "width": (x2 - x1) / w * 100,
                          "height": (y2 - y1) / h * 100, "rotation": 0, "rectanglelabels": [LABEL_OF_CLASS[int(cls)]]},
            })
        for v, wheel, role in rec.relations:
            result.append({"type": "relation", "from_id": str(wheel), "to_id": str(v), "direction": "right",
                           "labels": [role] if role else []})
        stated, n_lost = explicit_pairs(rec)
        lost += n_lost
        for rear, front in sorted(stated):
            result.append({"type": "relation", "from_id": str(rear), "to_id": str(front), "direction": "right",
                           "labels": [COUPLE]})
        scores = rec.scores
        data = {"image": image_url(rec.image, image_root), "camera": rec.camera, "frame_id": rec.frame_id}
        if rec.scene:
            data["scene"] = rec.scene
        tasks.append({"data": data, "predictions": [{
            "model_version": model_version, "score": round(float(scores.mean()), 4) if len(scores) else 0.0,
            "result": result}]})
    notes = []
    if lost:
        notes.append(f"{lost} vehicles have one rear and one front wheel that are not a couple: Label Studio reads "
                     f"them back as a couple (the roles give it)")
    return tasks, notes
