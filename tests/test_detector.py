"""BEV detector: grid/targets/decoding on hand-made inputs, weights loading (weights_only),
empty frames, data determinism, and the shipped model on a simple simulated frame."""
from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from adv3d_runner.autonomy.detector import (DEFAULT_MODEL_DIR, BevDetector, DetectorConfig, PixorNet,  # noqa: E402
                                            decode, encode_targets, load_detector, rotated_nms, save_detector,
                                            voxelize)
from adv3d_runner.autonomy.interface import Detections  # noqa: E402
from adv3d_runner.errors import FileFormatError  # noqa: E402
from adv3d_runner.geometry.boxes import iou_pairwise  # noqa: E402

SHIPPED = DEFAULT_MODEL_DIR / "config.json"


def _gt() -> np.ndarray:
    return np.array([[20.0, 3.5, 4.7, 1.9, 0.05], [35.0, -3.4, 14.5, 2.55, -0.1],
                     [8.0, 0.0, 4.2, 1.8, np.pi - 0.02], [45.0, 10.0, 4.5, 1.8, 1.2]])


@pytest.mark.parametrize("res", [0.2, 0.25, 0.4])
def test_grid_shapes_multiple_of_8(res):
    cfg = DetectorConfig(resolution=res)
    nx, ny = cfg.grid_shape
    assert nx % 8 == 0 and ny % 8 == 0
    assert nx * res >= cfg.x_range[1] - cfg.x_range[0] - 1e-9
    grid = voxelize(np.zeros((0, 4), np.float32), cfg)
    assert grid.shape == (cfg.in_channels, nx, ny) and not grid.any()


def test_voxelize_places_points_in_cells():
    cfg = DetectorConfig(resolution=0.25)
    pts = np.array([[10.1, 2.1, 1.0, 0.5], [10.1, 2.1, 0.05, 0.5],   # second one is road (below z_edges[0])
                    [-30.0, 0.0, 1.0, 0.0], [10.1, 2.1, 2.0, 0.0]], np.float32)
    g = voxelize(pts, cfg)
    i = int((10.1 - cfg.x_range[0]) / 0.25)
    j = int((2.1 - cfg.y_range[0]) / 0.25)
    slice_1m = np.searchsorted(cfg.z_edges, 1.0, side="right") - 1
    slice_2m = np.searchsorted(cfg.z_edges, 2.0, side="right") - 1
    assert g[slice_1m, i, j] == 1 and g[slice_2m, i, j] == 1
    assert g[:-1].sum() == 2                                    # the road and out-of-grid points are dropped
    assert g[-1, i, j] == pytest.approx(np.log1p(2) / np.log(64))


@pytest.mark.parametrize("res", [0.2, 0.25, 0.4])
def test_encode_decode_roundtrip(res):
    """Perfect network outputs (the targets themselves) decode to the ground-truth boxes."""
    cfg = DetectorConfig(resolution=res)
    gt = _gt()
    score, weight, reg = encode_targets(gt, cfg)
    assert score.sum() >= len(gt) and weight.min() == 1.0
    dets = decode(score * 0.9, reg, cfg)
    assert len(dets) == len(gt)
    iou = iou_pairwise(gt, dets.boxes)
    assert np.all(iou.max(axis=1) > 0.999)
    assert np.allclose(dets.scores, 0.9)


def test_ignore_boxes_zero_weight():
    cfg = DetectorConfig()
    score, weight, _ = encode_targets(_gt()[:1], cfg, ignore_boxes=_gt()[1:2])
    assert (weight == 0).sum() > 10
    assert np.all(weight[score > 0] == 1)


def test_decode_hand_made_heatmap_and_nms():
    """Three cells of one car (overlapping boxes) and one far car: NMS keeps two boxes, the
    higher-scored car first, the cluster's boxes averaged by score."""
    cfg = DetectorConfig(resolution=0.25, score_threshold=0.3)
    ox, oy = cfg.out_shape
    s = np.zeros((ox, oy))
    gt = np.array([[20.0, 0.0, 4.5, 1.8, 0.0], [40.0, -4.0, 4.5, 1.8, 0.1]])
    _, _, reg = encode_targets(gt, cfg)
    cx = lambda x: int((x - cfg.x_range[0]) / cfg.out_cell)  # noqa: E731
    cy = lambda y: int((y - cfg.y_range[0]) / cfg.out_cell)  # noqa: E731
    s[cx(20.0), cy(0.0)] = 0.9
    s[cx(20.0) + 1, cy(0.0)] = 0.8
    s[cx(20.0) - 1, cy(0.0)] = 0.7
    s[cx(40.0), cy(-4.0)] = 0.6
    s[cx(55.0), cy(15.0)] = 0.2        # below the threshold
    dets = decode(s, reg, cfg)
    assert isinstance(dets, Detections) and dets.boxes.shape == (2, 5) and dets.scores.shape == (2,)
    assert np.allclose(dets.scores, [0.9, 0.6])
    assert np.all(np.diag(iou_pairwise(gt, dets.boxes)) > 0.99)
    # Without NMS-suppression (threshold 1) every cell survives.
    b, sc = rotated_nms(np.repeat(gt[:1], 3, axis=0), np.array([0.5, 0.9, 0.7]), iou_threshold=1.0)
    assert len(b) == 3 and np.all(np.diff(sc) <= 0)
    b, sc = rotated_nms(np.repeat(gt[:1], 3, axis=0), np.array([0.5, 0.9, 0.7]), iou_threshold=0.1)
    assert len(b) == 1 and sc[0] == 0.9
    assert rotated_nms(np.zeros((0, 5)), np.zeros(0), 0.1)[0].shape == (0, 5)


def _nms_by_definition(boxes, scores, iou_threshold, max_keep=None):
    """Greedy rotated NMS with score voting from the full IoU matrix (``iou_pairwise``), the
    straightforward way: the reference the detector's lazy NMS must match bit for bit."""
    order = np.argsort(-scores, kind="stable")
    boxes, scores = boxes[order], scores[order]
    iou = iou_pairwise(boxes, boxes)
    radius = 0.5 * np.hypot(boxes[:, 2], boxes[:, 3])
    alive = np.ones(len(boxes), bool)
    out_b, out_s = [], []
    for i in range(len(boxes)):
        if not alive[i]:
            continue
        alive[i] = False
        near = alive & (np.hypot(boxes[:, 0] - boxes[i, 0], boxes[:, 1] - boxes[i, 1]) < radius + radius[i])
        sup = np.flatnonzero(near & (iou[i] > iou_threshold))
        alive[sup] = False
        cluster = np.concatenate([[i], sup])
        box = boxes[i].copy()
        if len(cluster) > 1:
            b, w = boxes[cluster], scores[cluster]
            agree = np.cos(b[:, 4] - box[4]) > 0.5
            b, w = b[agree], w[agree]
            w = w / w.sum()
            box[0:2] = w @ b[:, 0:2]
            box[2:4] = np.exp(w @ np.log(np.maximum(b[:, 2:4], 1e-3)))
            box[4] = math.atan2(w @ np.sin(b[:, 4]), w @ np.cos(b[:, 4]))
        out_b.append(box)
        out_s.append(scores[i])
        if max_keep is not None and len(out_b) >= max_keep:
            break
    return np.array(out_b).reshape(-1, 5), np.array(out_s)


def test_rotated_nms_equals_the_full_matrix_definition_bit_for_bit():
    """Clusters of overlapping candidates (as a detector's cells around cars give): the lazy
    keeper-against-near NMS keeps the same boxes, with the same bits, as the full IoU matrix."""
    rng = np.random.default_rng(7)
    for trial in range(60):
        cars = rng.normal(0.0, 6.0, (rng.integers(1, 8), 2))
        k = int(rng.integers(1, 60))
        centre = cars[rng.integers(0, len(cars), k)] + rng.normal(0.0, 0.6, (k, 2))
        dims = np.exp(rng.normal([1.5, 0.6], 0.15, (k, 2)))
        boxes = np.c_[centre, dims, rng.normal(0.3, 0.2 if trial % 2 else 2.0, k)]
        scores = rng.random(k)
        for thr in (0.05, 0.1, 0.5):
            got = rotated_nms(boxes, scores, thr, max_keep=20)
            want = _nms_by_definition(boxes, scores, thr, max_keep=20)
            assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()


def test_rotated_nms_equals_rotated_nms_numpy_bit_for_bit():
    """The lazy compiled NMS (one IoU batch per keeper) against the batch-of-all-near-pairs
    numpy version it replaced, kept as the reference: random clusters, ties, duplicates,
    zero and negative sizes, non-finite boxes (the fallback), every threshold and max_keep."""
    from adv3d_runner.autonomy.detector import rotated_nms_numpy

    rng = np.random.default_rng(11)
    for trial in range(120):
        cars = rng.normal(0.0, 6.0, (rng.integers(1, 8), 2))
        k = int(rng.integers(1, 80))
        boxes = np.c_[cars[rng.integers(0, len(cars), k)] + rng.normal(0.0, 0.6, (k, 2)),
                      np.exp(rng.normal([1.5, 0.6], 0.15, (k, 2))), rng.normal(0.3, 0.2 if trial % 2 else 2.0, k)]
        if trial % 7 == 0:
            boxes[rng.integers(0, k), 2] = 0.0
        if trial % 11 == 0:
            boxes[rng.integers(0, k), 3] = -1.0
        if trial % 13 == 0:
            boxes[rng.integers(0, k), 0] = np.nan
        if trial % 17 == 0:
            boxes[1:] = boxes[0]
        scores = np.round(rng.random(k), 1) if trial % 5 == 0 else rng.random(k)
        for thr in (-0.1, 0.0, 0.1, 0.5, 1.0):
            for max_keep in (None, 1, 3, 20):
                for vote in (True, False):
                    got = rotated_nms(boxes, scores, thr, max_keep, vote)
                    want = rotated_nms_numpy(boxes, scores, thr, max_keep, vote)
                    assert got[0].shape == want[0].shape
                    assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()


def test_empty_frame_gives_empty_detections():
    det = BevDetector(DetectorConfig(resolution=0.4))
    for pts in (np.zeros((0, 4), np.float32), np.zeros((0, 3)), np.array([[500.0, 0.0, 1.0]])):
        d = det.detect(pts)
        assert isinstance(d, Detections) and len(d) == 0 and d.boxes.shape == (0, 5)
    out = det.detect_batch([np.zeros((0, 3)), np.zeros((0, 3))])
    assert [len(d) for d in out] == [0, 0]


def test_output_shapes_random_net():
    cfg = DetectorConfig(resolution=0.4)
    net = PixorNet(cfg).eval()
    x = torch.zeros(2, cfg.in_channels, *cfg.grid_shape)
    with torch.inference_mode():
        s, b = net(x)
    assert tuple(s.shape) == (2, 1, *cfg.out_shape) and tuple(b.shape) == (2, 6, *cfg.out_shape)


def test_save_load_roundtrip_weights_only(tmp_path):
    torch.manual_seed(0)
    det = BevDetector(DetectorConfig(resolution=0.4, score_threshold=0.0))
    save_detector(det, tmp_path)
    back = load_detector(tmp_path)
    assert back.cfg == det.cfg
    for k, v in det.net.state_dict().items():
        assert torch.equal(v, back.net.state_dict()[k])
    pts = np.random.default_rng(0).uniform([0, -10, 0.5], [40, 10, 2], (500, 3)).astype(np.float32)
    back.inference_net = back.net  # the weights as saved (load_detector runs a BN-folded copy)
    a, b = det.detect(pts), back.detect(pts)
    assert np.allclose(a.boxes, b.boxes) and np.allclose(a.scores, b.scores)


def test_folded_batchnorm_is_the_same_network_up_to_rounding():
    """load_detector runs the net with its BatchNorms folded into the convolutions: the same
    outputs up to float32 rounding, and no BatchNorm left in the inference copy."""
    from adv3d_runner.autonomy.detector import PixorNet, fold_batchnorm

    torch.manual_seed(0)
    net = PixorNet(DetectorConfig(resolution=0.4)).eval()
    with torch.no_grad():  # non-trivial statistics, as after training
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
    folded = fold_batchnorm(net)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())  # the original is untouched
    x = torch.rand((1, net.stage1[0][0].in_channels) + DetectorConfig(resolution=0.4).grid_shape)
    with torch.inference_mode():
        (s0, b0), (s1, b1) = net(x), folded(x)
    assert torch.allclose(s0, s1, atol=1e-4) and torch.allclose(b0, b1, atol=1e-4)
    assert not torch.equal(s0, s1)  # folded, not the same module


class _Evil:
    def __reduce__(self):
        return (print, ("pickle code ran",))


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_pickled_weights_are_refused(tmp_path):
    det = BevDetector(DetectorConfig(resolution=0.4))
    save_detector(det, tmp_path)
    # A file that needs arbitrary unpickling (an object, not tensors) must be refused.
    torch.save({"net": _Evil()}, tmp_path / "detector.pt")
    with pytest.raises(FileFormatError, match="weights_only"):
        load_detector(tmp_path)
    (tmp_path / "detector.pt").write_bytes(pickle.dumps({"a": 1}))
    with pytest.raises(FileFormatError):
        load_detector(tmp_path)
    (tmp_path / "detector.pt").write_bytes(b"\x00garbage" * 10)            # corrupted file
    with pytest.raises(FileFormatError):
        load_detector(tmp_path)
    torch.save({"stage1.0.0.weight": torch.zeros(3)}, tmp_path / "detector.pt")  # wrong architecture
    with pytest.raises(FileFormatError, match="architecture"):
        load_detector(tmp_path)
    with pytest.raises(FileFormatError, match="config"):
        load_detector(tmp_path / "missing")


def test_data_generation_deterministic(tmp_path):
    from adv3d_runner.training.detector_data import TRAIN_SEED0, make_frames

    a = make_frames([TRAIN_SEED0 + 3], 2, library=None, cache_dir=tmp_path / "c1")
    b = make_frames([TRAIN_SEED0 + 3], 2, library=None, cache_dir=tmp_path / "c2")
    c = make_frames([TRAIN_SEED0 + 3], 2, library=None, cache_dir=tmp_path / "c1")  # from the cache
    for name in a.arrays():
        assert np.array_equal(a.arrays()[name], b.arrays()[name]), name
        assert np.array_equal(a.arrays()[name], c.arrays()[name]), name
    assert len(a) == 2 and len(a.points) > 1000 and len(a.boxes) >= 1
    assert list(tmp_path.joinpath("c1").glob("*.npz"))
    with np.load(next(tmp_path.joinpath("c1").glob("*.npz")), allow_pickle=False) as z:
        assert str(z["format"]) == "adv3d-detector-frames"


@pytest.mark.parametrize("folder", ["detector", "detector-fast"])
def test_shipped_detector_finds_car_20m_ahead(folder):
    """Ego on a straight road, one library car 20 m ahead in the ego's lane: each shipped
    detector (Autonomy-A's 0.25 m one and A-fast's 0.4 m one) finds it with BEV IoU > 0.5
    (ideal LiDAR: no noise)."""
    model = SHIPPED.parent.parent / folder
    if not (model / "detector.pt").is_file():
        pytest.skip(f"no shipped {folder}")
    from adv3d_runner.scene.generate import generate_scene
    from adv3d_runner.sensors.lidar import simulate_frame
    from adv3d_runner.sensors.world import LidarWorld, rig_from_scene
    from adv3d_runner.scene.background import background_mesh, REFLECTIVITY
    from adv3d_runner.shapes.library import load_library
    from adv3d_runner.scene.actors import choose_asset, actor_mesh

    scene = generate_scene(100_000, "train", layout="straight", density="free")
    v, f, kind = background_mesh(scene)
    world = LidarWorld(v, f, np.asarray(REFLECTIVITY, np.float32)[kind])
    lib = load_library()
    dims = np.array([4.7, 1.85, 1.45])
    mesh = actor_mesh(lib, choose_asset(lib, "sedan", dims, rule="nearest-size"), dims)
    world.add_actor(1, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    ego = scene.ego_poses()[0]
    c, s = np.cos(ego[2]), np.sin(ego[2])
    car = np.array([ego[0] + 20 * c, ego[1] + 20 * s, ego[2] + 0.03])
    frame = simulate_frame(world, rig_from_scene(scene), ego, car[None], rng=None)
    det = load_detector(model)
    assert det.cfg.resolution == {"detector": 0.25, "detector-fast": 0.4}[folder]
    dets = det.detect(frame.points)
    truth = np.array([[20.0, 0.0, dims[0], dims[1], 0.03]])
    assert len(dets) >= 1
    assert iou_pairwise(truth, dets.boxes).max() > 0.5
    assert dets.scores[np.argmax(iou_pairwise(truth, dets.boxes)[0])] > 0.5


@pytest.mark.slow
def test_train_cli_writes_model_and_report(tmp_path):
    """`adv3d train detector` on a tiny recipe writes loadable weights and a report."""
    import json

    from adv3d_runner.cli import main

    out = tmp_path / "model"
    rc = main(["-q", "train", "detector", "--scenes", "2", "--val-scenes", "1", "--frames-per-scene", "2",
               "--epochs", "1", "--resolution", "0.4", "--cache", str(tmp_path / "cache"), "--out", str(out)])
    assert rc == 0
    for name in ("detector.pt", "config.json", "training_report.json", "loss_curves.png"):
        assert (out / name).is_file(), name
    report = json.loads((out / "training_report.json").read_text())
    assert report["format"] == "adv3d-detector-training-report" and report["data"]["train_frames"] == 4
    assert len(report["history"]["epoch"]) == 1
    assert report["device"] == {"device": "cpu"} and report["seconds"]["train"] >= 0
    # the actors drew their meshes from the whole bundled library, recorded by fingerprint
    from adv3d_runner.shapes.library import library_fingerprint, load_library

    assert report["data"]["library_fingerprint"] == library_fingerprint(load_library())
    assert all("-lib-" in p.name for p in (tmp_path / "cache").rglob("*.npz"))
    det = load_detector(out)
    assert det.cfg.resolution == 0.4


def test_a_fast_is_autonomy_a_with_the_fast_detector_and_its_own_fingerprint():
    """--autonomy A-fast: the same tracker, predictor and planner as A, the 0.4 m detector, and
    the fingerprint of that detector in a run's versions (its results are another stack's)."""
    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.evaluator import EpisodeEvaluator
    from adv3d_runner.autonomy.stacks import make_stack

    a, fast = make_stack("A"), make_stack("A-fast")
    assert (a.detector.cfg.resolution, fast.detector.cfg.resolution) == (0.25, 0.4)
    assert type(a.predictor) is type(fast.predictor) and a.planner.config == fast.planner.config
    va = EpisodeEvaluator(QuerySettings(autonomy="A")).versions()
    vf = EpisodeEvaluator(QuerySettings(autonomy="A-fast")).versions()
    assert set(va["models"]) == {"detector", "predictor"} and set(vf["models"]) == {"detector-fast", "predictor"}
    assert va["models"]["predictor"] == vf["models"]["predictor"] and va["planner"] == vf["planner"]


def test_upsample_concat_is_interpolate_then_cat():
    import torch

    from adv3d_runner.autonomy.detector import upsample_concat

    g = torch.Generator().manual_seed(0)
    for coarse_hw, fine_hw in [((36, 24), (72, 48)), ((5, 3), (10, 6)), ((5, 3), (11, 7))]:
        coarse = torch.randn((2, 4) + coarse_hw, generator=g)
        skip = torch.randn((2, 3) + fine_hw, generator=g)
        ref = torch.cat([torch.nn.functional.interpolate(coarse, size=fine_hw, mode="nearest"), skip], dim=1)
        with torch.inference_mode():
            out = upsample_concat(coarse, skip)
        assert out.shape == ref.shape and torch.equal(out, ref)
        assert torch.equal(upsample_concat(coarse, skip), ref)  # the training (grad) path
        # the compiled copy takes contiguous float32; a strided or float64 coarse map the torch copy
        strided = coarse.transpose(2, 3).contiguous().transpose(2, 3)
        assert not strided.is_contiguous()
        with torch.inference_mode():
            assert torch.equal(upsample_concat(strided, skip), ref)
            assert torch.equal(upsample_concat(coarse.double(), skip.double()), ref.double())


def test_flat_forward_equals_the_folded_graph_module():
    """``flat_forward`` (direct conv2d / relu calls) gives the folded network's outputs bit for
    bit, follows in-place weight changes, and declines what it does not know."""
    from adv3d_runner.autonomy.detector import flat_forward, fold_batchnorm

    torch.manual_seed(3)
    torch.set_num_threads(1)  # as the detector runs (BevDetector threads=1); the thread count picks the kernels
    cfg = DetectorConfig(resolution=0.4)
    net = PixorNet(cfg).eval()
    gm = fold_batchnorm(net)
    flat = flat_forward(gm)
    assert flat is not None and flat_forward(net) is None
    x = (torch.rand(2, cfg.in_channels, *cfg.grid_shape) < 0.1).float()
    with torch.inference_mode():
        for _ in range(2):
            want, got = gm(x), flat(x)
            assert all(a.numpy().tobytes() == b.numpy().tobytes() for a, b in zip(want, got))
            gm.score.weight.mul_(1.5)  # in place: both see it
    gm.forward = lambda t: (t, t)  # a patched forward is left alone
    assert flat_forward(gm) is None
    det = BevDetector(cfg, net)
    det.inference_net = fold_batchnorm(net)
    pts = np.c_[np.random.default_rng(0).uniform([0, -10, 0.5], [40, 10, 2.0], (3000, 3)), np.ones(3000)]
    a = det.detect(pts, score_threshold=0.0)
    det._flat = (det.inference_net, None, {})  # the module path
    # (the two decodes of the same maps also agree only because decode_boxes makes its rows
    # contiguous: with numpy 1.26's arctan2 on strided rows this failed in ~1 run of 6, the
    # heading of one box a rounding step apart, depending on where the rows lay in memory)
    b = det.detect(pts, score_threshold=0.0)
    assert a.boxes.tobytes() == b.boxes.tobytes() and a.scores.tobytes() == b.scores.tobytes()



def test_blocked_forward_gives_the_flat_forwards_bits_and_is_checked_before_use(monkeypatch):
    """``blocked_forward`` (maps kept in oneDNN's layout between the 3 x 3 convolutions) gives
    ``flat_forward``'s outputs bit for bit on voxel grids, batched or not; the detector runs it
    only where that check passed for the input shape, and ``flat_forward`` otherwise."""
    from adv3d_runner.autonomy import detector as detector_mod
    from adv3d_runner.autonomy.detector import blocked_forward, flat_forward, fold_batchnorm

    torch.manual_seed(5)
    torch.set_num_threads(1)
    cfg = DetectorConfig(resolution=0.4)
    net = PixorNet(cfg).eval()
    with torch.no_grad():  # BatchNorm statistics away from the identity, so folding matters
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
    gm = fold_batchnorm(net)
    flat, blocked = flat_forward(gm), blocked_forward(gm)
    if blocked is None:
        pytest.skip("torch without oneDNN")
    assert blocked_forward(net) is None  # not a folded graph
    rng = np.random.default_rng(0)
    for batch in (1, 2):
        pts = [rng.uniform([-12, -24, 0.0], [60, 24, 4.0], (int(rng.integers(500, 20000)), 3))
               for _ in range(batch)]
        x = torch.from_numpy(np.stack([voxelize(p, cfg) for p in pts]))
        with torch.inference_mode():
            want, got = flat(x), blocked(x)
        assert [a.shape for a in want] == [b.shape for b in got]
        assert all(a.numpy().tobytes() == b.numpy().tobytes() for a, b in zip(want, got))
    det = BevDetector(cfg, net)
    det.inference_net = gm
    frame = np.c_[rng.uniform([0, -10, 0.5], [40, 10, 2.0], (3000, 3)), np.ones(3000)]
    first = det.detect(frame, score_threshold=0.0)
    (entry,) = det._flat[2].values()
    assert entry[0] is det._flat[1]  # flat_forward for the first blocked_after calls
    for _ in range(det.blocked_after):
        a = det.detect(frame, score_threshold=0.0)
    assert entry[0] is not det._flat[1] and entry[1] is None  # then the blocked forward, checked
    assert a.boxes.tobytes() == first.boxes.tobytes() and a.scores.tobytes() == first.scores.tobytes()
    monkeypatch.setattr(detector_mod, "same_outputs", lambda *args, **kw: False)  # a check that fails
    other = BevDetector(cfg, net)
    other.inference_net = gm
    other.blocked_after = 0
    b = other.detect(frame, score_threshold=0.0)
    (entry,) = other._flat[2].values()
    assert entry[0] is other._flat[1] and entry[1] is None  # stays with flat_forward
    assert b.boxes.tobytes() == first.boxes.tobytes() and b.scores.tobytes() == first.scores.tobytes()
    assert a.boxes.tobytes() == b.boxes.tobytes() and a.scores.tobytes() == b.scores.tobytes()


def test_bfloat16_precision_is_an_option_with_close_scores():
    """``precision="bfloat16"`` (not the default) runs the shipped network in bfloat16: the same
    output shapes, scores within 0.02 of float32's on a frame with cars, boxes of the same cars;
    the default stays float32, and an unknown precision is refused."""
    from adv3d_runner.errors import ConfigError

    if not (SHIPPED.parent / "detector.pt").is_file():
        pytest.skip("no shipped detector")
    ref, half = load_detector(), load_detector(precision="bfloat16")
    assert ref.precision == "float32" and half.precision == "bfloat16"
    rng = np.random.default_rng(1)
    cars = []
    for x, y in ((15.0, 0.0), (30.0, 3.5), (25.0, -3.5)):  # box-shaped point clouds of three cars
        n = 800
        cars.append(np.c_[rng.uniform(x - 2.3, x + 2.3, n), rng.uniform(y - 0.9, y + 0.9, n), rng.uniform(0.3, 1.5, n)])
    grid = voxelize(np.concatenate(cars), ref.cfg)[None]
    (s32, b32), (s16, b16) = ref._forward(grid), half._forward(grid)
    assert s16.shape == s32.shape and b16.shape == b32.shape and s16.dtype == np.float32
    assert 0 < np.abs(s16 - s32).max() < 0.02
    a, b = ref.detect(np.concatenate(cars)), half.detect(np.concatenate(cars))
    assert len(a) == len(b) and len(a) >= 1
    assert np.abs(a.boxes[:, :2] - b.boxes[:, :2]).max() < 0.5
    with pytest.raises(ConfigError):
        load_detector(precision="float16")
