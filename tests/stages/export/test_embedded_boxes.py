"""The operating-point search's relation model embedded once per box (``stages.export.embedded_boxes``) against the
shipped ONNX model run on every subset whole: the same scores and decisions, with an ensemble and flip averaging."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from deepword.inference.runtime import RELATION_FILES, OnnxRelation
from deepword.operating_point.search import SubsetRelation, search_operating_point
from deepword.relation_graph import subgraph
from deepword.word_format import load_image, open_dataset
from stages.export.embedded_boxes import EmbeddedBoxes
from stages.export.onnx_export import export_relation
from stages.relation.model import RelationEnsemble
from tests.stages.export.test_export_parity import random_graphs, small_net
from tests.stages.export.tiny_models import MAX_OBJECTS, RELATION_MODEL


@pytest.fixture(scope="module")
def ensemble_bundle(exported, tmp_path_factory):
    """The exported bundle with its relation model replaced by a two-network ensemble scored with flip averaging,
    deciding at a cosine of 0.1: untrained networks seldom reach 0.5, and the search should see claims."""
    bundle = tmp_path_factory.mktemp("ensemble_bundle")
    shutil.copytree(exported[0], bundle, dirs_exist_ok=True)
    net = RelationEnsemble([small_net(0), small_net(1)]).eval()
    export_relation(net, bundle / RELATION_FILES["dynamic"], RELATION_MODEL["backbone"]["input_size"], MAX_OBJECTS, static=False)
    meta = json.loads((bundle / "export.json").read_text())
    meta["relation"]["decode"].update(flip_average=True, threshold=0.1)
    (bundle / "export.json").write_text(json.dumps(meta))
    return net, bundle


def test_subsets_score_as_the_shipped_model_scores_them_whole(ensemble_bundle):
    torch.set_num_threads(1)
    net, bundle = ensemble_bundle
    shipped = OnnxRelation(bundle, "dynamic")
    assert shipped.flip_average
    graphs = dict(zip("abc", random_graphs([9, 4, 13], RELATION_MODEL["backbone"]["input_size"], seed=3), strict=True))
    embedded = EmbeddedBoxes(net, graphs, flip_average=True)
    rng = np.random.default_rng(0)
    images = ["a", "b", "c", "a", "c"]
    rows = [np.sort(rng.choice(len(graphs[i].classes), size=k, replace=False)) for i, k in zip(images, [5, 4, 7, 1, 13],
                                                                                               strict=True)]
    mine = embedded.scores(images, rows)
    theirs = shipped.scores([subgraph(graphs[i], r) for i, r in zip(images, rows, strict=True)])
    real = mine[3] >= 0
    pairs = real[:, :, None] & real[:, None, :]
    for a, b in zip(mine[:3], theirs[:3], strict=True):   # owner, couple, front
        where = pairs if a.ndim == 3 else real
        assert np.abs(a - b)[where].max() < 1e-5
    for a, b in zip(mine[3:], theirs[3:], strict=True):   # classes, candidates, coordinates as padded by the runtime
        np.testing.assert_array_equal(a, b)
    assert np.abs(theirs[0] * theirs[4]).max() > 0.05      # real scores were compared, not padding
    assert embedded.max_abs_diff_to(shipped.scores) < 1e-5
    # the check the export stage makes before the search: another network's scores are far off
    other = EmbeddedBoxes(RelationEnsemble([small_net(2), small_net(3)]).eval(), graphs, flip_average=True)
    assert other.max_abs_diff_to(shipped.scores) > 1e-2


def test_the_search_finds_the_same_point_with_each_box_embedded_once(ensemble_bundle, upstream):
    net, bundle = ensemble_bundle
    ds = open_dataset(upstream["data"])
    truths = ds.subset("test")
    rng = np.random.default_rng(1)
    # the labelled boxes as detections with drawn scores (ids 0..N-1, as detection records have them)
    detections = []
    for t in truths:
        boxes = t.boxes.copy()
        boxes[:, 4], boxes[:, 6] = rng.uniform(0.1, 0.9, len(boxes)), np.arange(len(boxes))
        detections.append(replace(t, boxes=boxes, relations=[], wheel_pairs=[]))
    def load(rec):
        return load_image(ds.root, rec)
    whole = SubsetRelation(OnnxRelation(bundle, "dynamic"), detections, load)
    shipped = OnnxRelation(bundle, "dynamic")
    once = SubsetRelation(shipped, detections, load,
                          embed=lambda graphs: EmbeddedBoxes(net, graphs, shipped.flip_average))
    assert whole.embedded is None and once.embedded is not None
    grid, sides = [0.1, 0.3, 0.5, 0.7], [[0.0], [0.0, 8.0]]
    chosen_whole, seen_whole = search_operating_point(truths, detections, whole, 2, grid, sides, 4.0)
    chosen_once, seen_once = search_operating_point(truths, detections, once, 2, grid, sides, 4.0)
    assert chosen_once == chosen_whole and seen_once == seen_whole
    assert len(once.predicted) == len(whole.predicted) > 10
    assert {k: (p.relations, p.wheel_pairs) for k, p in once.predicted.items()} == \
        {k: (p.relations, p.wheel_pairs) for k, p in whole.predicted.items()}
    assert any(p.relations for p in once.predicted.values())
