"""DINOv2-based retrieval methods: SALAD, MegaLoc, AnyLoc, SelaVPR (+ SelaVPR local features).

No real weights can be downloaded here, so:
- full-size architectures are built on the meta device and their state-dict keys/shapes pinned to the authors'
  code (numbers derived in the comments);
- the loading path is exercised with files written in the authors' layout (random tensors), found through
  $AEROLOC_WEIGHTS_DIR, then run on a real NAIP tile. AnyLoc and SelaVPR use a shrunken ViT there
  (``backbone_overrides``, a test-only conf) so the forward pass stays fast.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import rasterio
import torch
from rasterio.windows import Window

from aeroloc.core.errors import AerolocError, WeightsNotFound
from aeroloc.matching.models.selavpr_local import SelaVPRLocal, SelaVPRMutualNN
from aeroloc.retrieval.models import build_method, method_class
from aeroloc.retrieval.models.anyloc import AnyLoc, hard_vlad
from aeroloc.retrieval.models.dinov2 import DinoV2
from aeroloc.retrieval.models.salad import log_optimal_transport

TINY_VIT = {"embed_dim": 64, "num_heads": 2, "depth": 3}  # test-only size (the released files need the real one)


@pytest.fixture(scope="module")
def naip_tiles(naip_map):
    """Two 200 x 200 px windows (1 km) of the real NAIP map, RGB uint8."""
    if not naip_map.is_file():
        pytest.skip(f"{naip_map} missing")
    with rasterio.open(naip_map) as src:
        tiles = [src.read((1, 2, 3), window=Window(col, row, 200, 200)) for col, row in ((300, 200), (600, 450))]
    return [np.ascontiguousarray(np.moveaxis(t, 0, -1)) for t in tiles]


@pytest.fixture
def weights_dir(tmp_path, monkeypatch):
    """An empty weights folder; cache elsewhere; no download attempts."""
    folder = tmp_path / "weights"
    folder.mkdir()
    monkeypatch.setenv("AEROLOC_WEIGHTS_DIR", str(folder))
    monkeypatch.setenv("AEROLOC_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("AEROLOC_OFFLINE", "1")
    return folder


def _on_meta(cls, conf=None):
    with torch.device("meta"):
        return cls(conf)


def _shapes(module) -> dict[str, tuple]:
    return {k: tuple(v.shape) for k, v in module.state_dict().items()}


def _check_descriptors(desc: torch.Tensor, dim: int, n: int):
    assert desc.shape == (n, dim)
    assert torch.isfinite(desc).all()
    assert torch.allclose(desc.norm(dim=1), torch.ones(n), atol=1e-5)


# --- architectures on the meta device ------------------------------------------------------------------------
# DINOv2 (dinov2/models/vision_transformer.py, hub/backbones.py, block_chunks=0): 5 top-level tensors (cls_token,
# pos_embed, mask_token, patch_embed.proj.weight/bias) + 14 per block (norm1 x2, attn.qkv x2, attn.proj x2,
# ls1.gamma, norm2 x2, mlp.fc1/fc2 or mlp.w12/w3 x4, ls2.gamma) + norm x2. pos_embed: 1 + (518/14)^2 = 1370 rows.
# SwiGLUFFNFused hidden for ViT-G: (int(4*1536*2/3) + 7) // 8 * 8 = 4096, so w12 is 2*4096 x 1536.
@pytest.mark.parametrize(
    "arch, n_keys, pinned",
    [
        (
            "vits14",
            5 + 12 * 14 + 2,
            {"pos_embed": (1, 1370, 384), "blocks.11.attn.qkv.weight": (1152, 384), "mask_token": (1, 384)},
        ),
        (
            "vitb14",
            5 + 12 * 14 + 2,
            {
                "patch_embed.proj.weight": (768, 3, 14, 14),
                "blocks.11.mlp.fc1.weight": (3072, 768),
                "cls_token": (1, 1, 768),
            },
        ),
        (
            "vitl14",
            5 + 24 * 14 + 2,
            {"pos_embed": (1, 1370, 1024), "blocks.23.ls2.gamma": (1024,), "blocks.23.mlp.fc2.weight": (1024, 4096)},
        ),
        (
            "vitg14",
            5 + 40 * 14 + 2,
            {
                "pos_embed": (1, 1370, 1536),
                "blocks.39.mlp.w12.weight": (8192, 1536),
                "blocks.39.mlp.w3.weight": (1536, 4096),
                "blocks.39.ls1.gamma": (1536,),
                "norm.weight": (1536,),
            },
        ),
    ],
)
def test_dinov2_state_dict_matches_hub_checkpoints(arch, n_keys, pinned):
    with torch.device("meta"):
        shapes = _shapes(DinoV2(arch))
    assert len(shapes) == n_keys
    for key, shape in pinned.items():
        assert shapes[key] == shape, key


# SALAD (hubconf.py: VPRModel(backbone dinov2_vitb14, SALAD(768, 64 clusters, 128, token 256))): 175 DINOv2-B keys
# under backbone.model. + 13 aggregator tensors (token_features.0/2, cluster_features.0/3, score.0/3: 2 each,
# dust_bin). MegaLoc (megaloc_model.py): the same with aggregator.agg. + aggregator.linear (2) = 190 and
# cluster_dim 256: linear 64*256 + 256 = 16640 -> 8448. AnyLoc: ViT-G blocks 0..31 only (5 + 32*14 + 2) + c_centers.
# SelaVPR (network.py + backbone/dinov2/block.py): ViT-L with 8 adapter tensors per block (adapter1/2.D_fc1/2,
# hidden int(1024 * 0.5) = 512): 5 + 24*22 + 2 = 535, + aggregation.1.p + LocalAdapt.upconv1/2 (4) = 540.
@pytest.mark.parametrize(
    "name, n_keys, dim, side, pinned",
    [
        (
            "salad",
            175 + 13,
            8448,
            322,
            {
                "backbone.model.pos_embed": (1, 1370, 768),
                "backbone.model.blocks.11.ls2.gamma": (768,),
                "aggregator.token_features.2.weight": (256, 512),
                "aggregator.cluster_features.3.weight": (128, 512, 1, 1),
                "aggregator.score.3.weight": (64, 512, 1, 1),
                "aggregator.dust_bin": (),
            },
        ),
        (
            "megaloc",
            175 + 13 + 2,
            8448,
            322,
            {
                "backbone.model.blocks.0.attn.qkv.weight": (2304, 768),
                "aggregator.agg.token_features.0.weight": (512, 768),
                "aggregator.agg.cluster_features.3.weight": (256, 512, 1, 1),
                "aggregator.linear.weight": (8448, 16640),
                "aggregator.linear.bias": (8448,),
            },
        ),
        (
            "anyloc",
            5 + 32 * 14 + 2 + 1,
            32 * 1536,
            322,
            {
                "backbone.blocks.31.attn.qkv.weight": (4608, 1536),
                "backbone.blocks.31.mlp.w12.weight": (8192, 1536),
                "c_centers": (32, 1536),
            },
        ),
        (
            "selavpr",
            5 + 24 * 22 + 2 + 1 + 4,
            1024,
            224,
            {
                "backbone.blocks.0.adapter1.D_fc1.weight": (512, 1024),
                "backbone.blocks.23.adapter2.D_fc2.weight": (1024, 512),
                "backbone.blocks.23.mlp.fc1.weight": (4096, 1024),
                "aggregation.1.p": (1,),
                "LocalAdapt.upconv1.weight": (1024, 256, 3, 3),
                "LocalAdapt.upconv2.weight": (256, 128, 3, 3),
            },
        ),
    ],
)
def test_method_state_dicts_match_authors_code(name, n_keys, dim, side, pinned):
    model = _on_meta(method_class(name))
    shapes = _shapes(model)
    assert len(shapes) == n_keys
    for key, shape in pinned.items():
        assert shapes[key] == shape, key
    assert model.dim == dim
    image = np.zeros((150, 260, 3), np.uint8)
    assert tuple(model.preprocess(image).shape) == (3, side, side)


def test_anyloc_keeps_blocks_up_to_its_layer_from_the_full_vitg_checkpoint():
    model = _on_meta(AnyLoc)
    with torch.device("meta"):
        full = DinoV2("vitg14").state_dict()
    model.load_checkpoint(full)  # meta -> meta: checks keys and shapes, copies nothing
    assert not any(k.startswith("backbone.blocks.32.") for k in model.state_dict())
    truncated = {k: v for k, v in full.items() if not k.startswith("blocks.39.")}
    with pytest.raises(AerolocError, match=r"blocks\.39"):
        model.load_checkpoint(truncated)


# --- pieces checked against hand computations -------------------------------------------------------------
def test_hard_vlad_hand_computed():
    centers = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    desc = torch.tensor([[[1.0, 0.0], [0.6, 0.8], [0.8, 0.6]]])
    # d0, d2 -> c0 (residuals (0, 0) + (-0.2, 0.6)); d1 -> c1 (residual (0.6, -0.2)); c2 is empty
    expected = torch.tensor([[-1.0, 3.0, 3.0, -1.0, 0.0, 0.0]]) / math.sqrt(20)
    assert torch.allclose(hard_vlad(desc, centers), expected, atol=1e-6)


def test_sinkhorn_gives_each_token_unit_mass_and_needs_more_tokens_than_clusters():
    scores = torch.randn(2, 8, 30, generator=torch.Generator().manual_seed(0))
    plan = log_optimal_transport(scores, torch.tensor(1.0)).exp()
    assert plan.shape == (2, 9, 30)
    assert torch.allclose(plan.sum(dim=1), torch.ones(2, 30), atol=1e-5)  # clusters + dustbin per token
    with pytest.raises(AerolocError, match="more image patches"):
        log_optimal_transport(torch.randn(1, 8, 8), torch.tensor(1.0))


def test_dinov2_sizes_and_value_facet_hook():
    vit = DinoV2("vitg14", TINY_VIT).eval()
    x = torch.randn(1, 3, 224, 322)
    with torch.inference_mode():
        tokens = vit.tokens(x)
        assert tokens.shape == (1, 1 + 16 * 23, 64)
        assert vit.interpolate_pos_encoding(37, 37) is vit.pos_embed
        # the early-stopping value facet equals the value part of qkv seen during a full forward pass
        seen = {}
        handle = vit.blocks[1].attn.qkv.register_forward_hook(lambda m, i, o: seen.setdefault("qkv", o))
        vit.tokens(x)
        handle.remove()
        assert torch.allclose(vit.value_facet(x, 1), seen["qkv"][:, 1:, 128:], atol=1e-6)
    with pytest.raises(AerolocError, match="multiples of 14"):
        vit.tokens(torch.randn(1, 3, 224, 230))


def test_mutual_nn_hand_computed():
    d0 = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.7, 0.71, 0]], np.float32)
    d1 = np.array([[0, 0, 1], [0.9, 0.1, 0], [0.6, 0.8, 0]], np.float32)
    d0 /= np.linalg.norm(d0, axis=1, keepdims=True)
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    f0, f1 = {"descriptors": d0}, {"descriptors": d1}
    # d0[1]'s best is d1[2], but d1[2] prefers d0[3] (0.99 > 0.8): not mutual
    matches, scores = SelaVPRMutualNN().match(f0, f1)
    assert matches.tolist() == [[0, 1], [2, 0], [3, 2]]
    assert np.allclose(scores, [d0[0] @ d1[1], 1.0, d0[3] @ d1[2]], atol=1e-6)
    matches, _ = SelaVPRMutualNN({"min_similarity": 0.995}).match(f0, f1)
    assert matches.tolist() == [[2, 0]]
    empty, empty_scores = SelaVPRMutualNN().match({"descriptors": np.zeros((0, 3), np.float32)}, f1)
    assert empty.shape == (0, 2) and empty_scores.shape == (0,)


# --- loading the authors' files, then a real tile ---------------------------------------------------------
def _random_model_state(cls, conf=None, seed=1):
    """A randomly initialised state dict standing in for the released weights."""
    torch.manual_seed(seed)
    return cls(conf).state_dict()


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, filename, probe",
    [
        ("salad", "dino_salad.ckpt", "aggregator.score.3.weight"),
        ("megaloc", "megaloc.torch", "aggregator.linear.bias"),
    ],
)
def test_salad_and_megaloc_load_release_file_and_describe_naip(name, filename, probe, weights_dir, naip_tiles):
    state = _random_model_state(method_class(name))
    torch.save(state, weights_dir / filename)  # the release files are flat state dicts with these keys
    qkv = "backbone.model.blocks.11.attn.qkv.weight"
    expected = {k: state[k].clone() for k in (probe, qkv)}
    del state
    model = build_method(name, {"resize": 224})  # 16 x 16 patches instead of 23 x 23: same weights, faster
    loaded = model.state_dict()
    for key, value in expected.items():
        assert torch.equal(loaded[key], value), key
    batch = torch.stack([model.preprocess(t) for t in naip_tiles])
    with torch.inference_mode():
        desc = model(batch)
        if name == "salad":
            assert torch.allclose(model(batch[:1])[0], desc[0], atol=1e-5)  # no leakage across the batch
    _check_descriptors(desc, 8448, 2)
    assert float(desc[0] @ desc[1]) < 0.9999  # different places, different descriptors


def test_anyloc_loads_dinov2_file_and_vocabulary(weights_dir, naip_tiles):
    conf = {"backbone_overrides": TINY_VIT, "layer": 1}  # test-only conf: 64-d ViT, value facet of block 1
    with pytest.raises(WeightsNotFound) as err:
        build_method("anyloc", conf)
    assert "https://dl.fbaipublicfiles.com/dinov2/dinov2_vitg14/dinov2_vitg14_pretrain.pth" in str(err.value)
    torch.manual_seed(2)
    vit_state = DinoV2("vitg14", TINY_VIT).state_dict()  # official layout: bare keys, all blocks
    torch.save(vit_state, weights_dir / "dinov2_vitg14_pretrain.pth")
    with pytest.raises(WeightsNotFound) as err:
        build_method("anyloc", conf)
    vocab_name = "dinov2_vitg14_l1_value_c32_aerial_c_centers.pt"
    assert f"https://github.com/AnyLoc/DINO/releases/download/v1/{vocab_name}" in str(err.value)
    centers = torch.randn(32, 64)
    torch.save(centers, weights_dir / vocab_name)  # the release holds a bare tensor
    model = build_method("anyloc", conf)
    assert len(model.backbone.blocks) == 2  # block 2 of the file is dropped
    assert torch.equal(model.backbone.blocks[1].attn.qkv.weight, vit_state["blocks.1.attn.qkv.weight"])
    assert torch.equal(model.c_centers, centers)
    assert model.dim == 32 * 64
    with torch.inference_mode():
        desc = model(torch.stack([model.preprocess(t) for t in naip_tiles]))
    _check_descriptors(desc, 32 * 64, 2)


def test_selavpr_loads_checkpoint_and_extracts_local_features(weights_dir, naip_tiles):
    conf = {"backbone_overrides": {"embed_dim": 64, "num_heads": 2, "depth": 2}}  # test-only conf
    with pytest.raises(WeightsNotFound) as err:
        build_method("selavpr", conf)
    assert "1vy05l0JTEgr6n8iSoz_P_yjWfEzFPAkV" in str(err.value)
    assert str(weights_dir.parent / "cache" / "weights" / "SelaVPR_msls.pth") in str(err.value)
    from aeroloc.retrieval.models.selavpr import SelaVPR

    state = {k: v.clone() for k, v in _random_model_state(SelaVPR, conf).items()}
    # util.save_checkpoint of a DataParallel model: nested dict, "module." prefix
    torch.save(
        {
            "epoch_num": 3,
            "model_state_dict": {f"module.{k}": v for k, v in state.items()},
            "best_r5": 90.0,
            "not_improved_num": 0,
        },
        weights_dir / "SelaVPR_msls.pth",
    )
    model = build_method("selavpr", conf)
    for key in ("aggregation.1.p", "backbone.blocks.1.adapter2.D_fc1.weight", "LocalAdapt.upconv2.weight"):
        assert torch.equal(model.state_dict()[key], state[key]), key
    with torch.inference_mode():
        desc = model(torch.stack([model.preprocess(t) for t in naip_tiles]))
    _check_descriptors(desc, 64, 2)

    tile = naip_tiles[0]
    feats = SelaVPRLocal(model=model).extract(tile)
    kp, d = feats["keypoints"], feats["descriptors"]
    assert kp.shape == (61 * 61, 2) and d.shape == (61 * 61, 128)  # 224 px -> 16 patches -> 4*16 - 3 = 61
    assert np.allclose(np.linalg.norm(d, axis=1), 1, atol=1e-4)
    assert feats["image_size"].tolist() == [200, 200]
    # cell 0 at input pixel 7, cell 60 at 3.5 * 60 + 7 = 217, scaled by 200/224, pixel-index convention
    assert np.isclose(kp[:, 0].min(), 7 * 200 / 224 - 0.5) and np.isclose(kp[:, 0].max(), 217 * 200 / 224 - 0.5)
    mask = np.ones(tile.shape[:2], bool)
    mask[:, :100] = False  # e.g. a black border on the left half
    masked = SelaVPRLocal(model=model).extract(tile, mask)["keypoints"]
    assert 0 < len(masked) < len(kp) and (masked[:, 0] >= 99.5).all()
    matches, _ = SelaVPRMutualNN().match(feats, feats)  # an image against itself: every feature is its own MNN
    assert len(matches) == len(kp) and (matches[:, 0] == matches[:, 1]).all()


def test_missing_release_file_names_url_and_target(weights_dir):
    with pytest.raises(WeightsNotFound) as err:
        build_method("salad")
    msg = str(err.value)
    assert "https://github.com/serizba/salad/releases/download/v1.0.0/dino_salad.ckpt" in msg
    assert str(weights_dir.parent / "cache" / "weights" / "dino_salad.ckpt") in msg
