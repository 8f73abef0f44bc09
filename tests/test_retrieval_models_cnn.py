"""CNN global-descriptor methods (NetVLAD, CosPlace, EigenPlaces, MixVPR, BoQ-ResNet50).

The real checkpoints cannot be downloaded here, so these tests pin the authors' checkpoint layouts (key
counts and shapes derived from their code, on the ``meta`` device: no memory, no time), then run the real
loading path on random weights saved in that layout, and one real NAIP tile through each model.
"""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
import torch
from rasterio.windows import Window

from aeroloc.core.errors import AerolocError, WeightsNotFound
from aeroloc.core.weights import cache_dir
from aeroloc.retrieval.models import build_method, method_class
from aeroloc.retrieval.models.netvlad import NetVLADLayer, read_matconvnet, state_from_matconvnet


def meta_model(name: str, conf: dict | None = None):
    with torch.device("meta"):
        return method_class(name)(conf)


# Key counts. torchvision state dicts: resnet18 122 entries, resnet50 320, resnet101 626, resnet152 932
# (fc.weight/bias included; layer4 of resnet50 = 60 entries); vgg16.features 26 (13 convs x weight+bias).
# CosPlace/EigenPlaces (GeoLocalizationNet: children()[:-2] + [L2Norm, GeM, Flatten, Linear, L2Norm]):
#   ResNet: n - 2 (fc) + 1 (aggregation.1.p) + 2 (aggregation.3) = n + 1; VGG16 (features[:-2]): 26 + 3 = 29.
# MixVPR (VPRModel, layers_to_crop=[4]): 320 - 60 (layer4) - 2 (fc) = 258 backbone.model.* entries, plus
#   4 mixer layers x (LayerNorm 2 + Linear 2 + Linear 2) = 24, channel_proj 2, row_proj 2 -> 286.
# BoQ ResNet50 (hubconf get_trained_boq): 258 backbone.net.* + proj_c 2 + norm_input 2 + fc 2 + 2 BoQ blocks x
#   25 (queries 1, TransformerEncoderLayer 12, self_attn 4, norm_q 2, cross_attn 4, norm_out 2) -> 314.
# NetVLAD (hloc / VPR-methods-evaluation): 26 VGG16 conv entries + score_proj.weight + centers (+ whiten
#   weight/bias for 4096-d) + our `mean` buffer (the checkpoint's averageImage) -> 29 / 31.
# Shapes: torchvision layer sizes and the authors' configs (MixVPR: 20 x 20 = 400 positions, 1024 channels,
# README table C x R = 1024 x 4 / 256 x 2 / 64 x 2; BoQ: proj 512, 64 queries, 8 heads -> in_proj 3 x 512,
# row_dim 32; NetVLAD: 64 clusters x 512 channels, whitening 32768 -> 4096).
LAYOUTS = [
    (
        "cosplace",
        {"backbone": "ResNet18", "dim": 32},
        123,
        {
            "backbone.0.weight": (64, 3, 7, 7),
            "backbone.7.1.conv2.weight": (512, 512, 3, 3),
            "aggregation.1.p": (1,),
            "aggregation.3.weight": (32, 512),
            "aggregation.3.bias": (32,),
        },
    ),
    (
        "cosplace",
        {"backbone": "ResNet50", "dim": 2048},
        321,
        {"backbone.7.2.conv3.weight": (2048, 512, 1, 1), "aggregation.3.weight": (2048, 2048)},
    ),
    (
        "cosplace",
        {"backbone": "ResNet101", "dim": 1024},
        627,
        {"backbone.6.22.conv3.weight": (1024, 256, 1, 1), "aggregation.3.weight": (1024, 2048)},
    ),
    (
        "cosplace",
        {"backbone": "ResNet152", "dim": 512},
        933,
        {"backbone.6.35.bn3.running_var": (1024,), "aggregation.3.weight": (512, 2048)},
    ),
    (
        "cosplace",
        {"backbone": "VGG16", "dim": 64},
        29,
        {"backbone.0.weight": (64, 3, 3, 3), "backbone.28.weight": (512, 512, 3, 3), "aggregation.3.weight": (64, 512)},
    ),
    ("eigenplaces", {"backbone": "ResNet18", "dim": 256}, 123, {"aggregation.3.weight": (256, 512)}),
    (
        "eigenplaces",
        {"backbone": "ResNet50", "dim": 2048},
        321,
        {
            "backbone.4.0.downsample.0.weight": (256, 64, 1, 1),
            "aggregation.1.p": (1,),
            "aggregation.3.weight": (2048, 2048),
        },
    ),
    ("eigenplaces", {"backbone": "ResNet101", "dim": 128}, 627, {"aggregation.3.weight": (128, 2048)}),
    ("eigenplaces", {"backbone": "VGG16", "dim": 512}, 29, {"aggregation.3.weight": (512, 512)}),
    (
        "mixvpr",
        {"dim": 4096},
        286,
        {
            "backbone.model.conv1.weight": (64, 3, 7, 7),
            "backbone.model.layer3.5.conv3.weight": (1024, 256, 1, 1),
            "aggregator.mix.0.mix.0.weight": (400,),
            "aggregator.mix.3.mix.3.weight": (400, 400),
            "aggregator.channel_proj.weight": (1024, 1024),
            "aggregator.row_proj.weight": (4, 400),
            "aggregator.row_proj.bias": (4,),
        },
    ),
    (
        "mixvpr",
        {"dim": 512},
        286,
        {"aggregator.channel_proj.weight": (256, 1024), "aggregator.row_proj.weight": (2, 400)},
    ),
    (
        "mixvpr",
        {"dim": 128},
        286,
        {"aggregator.channel_proj.weight": (64, 1024), "aggregator.row_proj.weight": (2, 400)},
    ),
    (
        "boq",
        None,
        314,
        {
            "backbone.net.0.weight": (64, 3, 7, 7),
            "backbone.net.6.5.conv3.weight": (1024, 256, 1, 1),
            "aggregator.proj_c.weight": (512, 1024, 3, 3),
            "aggregator.norm_input.weight": (512,),
            "aggregator.boqs.0.queries": (1, 64, 512),
            "aggregator.boqs.1.encoder.self_attn.in_proj_weight": (1536, 512),
            "aggregator.boqs.1.encoder.linear1.weight": (2048, 512),
            "aggregator.boqs.0.cross_attn.out_proj.weight": (512, 512),
            "aggregator.fc.weight": (32, 128),
        },
    ),
    (
        "netvlad",
        {"dim": 4096},
        31,
        {
            "backbone.28.weight": (512, 512, 3, 3),
            "netvlad.score_proj.weight": (64, 512, 1),
            "netvlad.centers": (512, 64),
            "whiten.weight": (4096, 32768),
            "whiten.bias": (4096,),
        },
    ),
    ("netvlad", {"dim": 32768}, 29, {"backbone.26.bias": (512,), "netvlad.centers": (512, 64)}),
]


@pytest.mark.parametrize("name,conf,n_keys,shapes", LAYOUTS, ids=lambda v: str(v) if isinstance(v, (str, dict)) else "")
def test_state_dict_matches_authors_layout(name, conf, n_keys, shapes):
    model = meta_model(name, conf)
    state = model.state_dict()
    assert len(state) == n_keys
    for key, shape in shapes.items():
        assert tuple(state[key].shape) == shape, key
    assert model.dim == (conf or {}).get("dim", model.default_conf["dim"])


@pytest.mark.parametrize(
    "name,conf,url",
    [
        # URLs from the authors' hubconf.py / README / VPR-methods-evaluation
        (
            "cosplace",
            {"backbone": "ResNet18", "dim": 32},
            "https://github.com/gmberton/CosPlace/releases/download/v1.0/ResNet18_32_cosplace.pth",
        ),
        (
            "eigenplaces",
            {"backbone": "ResNet101", "dim": 2048},
            "https://github.com/gmberton/EigenPlaces/releases/download/v1.0/ResNet101_2048_eigenplaces.pth",
        ),
        ("boq", None, "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/resnet50_16384.pth"),
        ("netvlad", {"weights": "TokyoTM"}, "https://cvg-data.inf.ethz.ch/hloc/netvlad/TokyoTM_struct.mat"),
    ],
)
def test_weight_urls(name, conf, url):
    assert meta_model(name, conf).weight_source.url == url


def test_every_variant_has_its_own_weights_file():
    names = []
    for name in ("cosplace", "eigenplaces"):
        cls = method_class(name)
        names += [
            meta_model(name, {"backbone": b, "dim": d}).weight_source.filename
            for b, dims in cls.AVAILABLE.items()
            for d in dims
        ]
    names += [meta_model("mixvpr", {"dim": d}).weight_source.filename for d in (128, 512, 4096)]
    names += [meta_model("netvlad", {"weights": w}).weight_source.filename for w in ("Pitts30K", "TokyoTM")]
    names.append(meta_model("boq").weight_source.filename)
    assert len(names) == 30 + 13 + 3 + 2 + 1  # cosplace, eigenplaces (hubconf tables), mixvpr, netvlad, boq
    assert len(set(names)) == len(names)


@pytest.mark.parametrize(
    "name,conf",
    [
        ("cosplace", {"backbone": "ResNet18", "dim": 2048}),  # not released
        ("cosplace", {"backbone": "ResNet34", "dim": 512}),
        ("eigenplaces", {"backbone": "ResNet152", "dim": 512}),
        ("mixvpr", {"dim": 1024}),
        ("mixvpr", {"resize": 384}),
        ("boq", {"dim": 12288}),
        ("netvlad", {"dim": 1024}),
        ("netvlad", {"weights": "MSLS"}),
    ],
)
def test_unknown_variant_is_a_clear_error(name, conf):
    with pytest.raises(AerolocError):
        meta_model(name, conf)


# -- the loading path on real data ------------------------------------------------------------------


@pytest.fixture(scope="module")
def naip_tile(naip_map) -> np.ndarray:
    with rasterio.open(naip_map) as src:
        return np.moveaxis(src.read((1, 2, 3), window=Window(300, 200, 300, 300)), 0, -1)


def write_netvlad_mat(path, state: dict, whiten: bool, mean_image: np.ndarray) -> None:
    """The hloc MatConvNet struct: net.layers{1..34} (conv weights S x S x IN x OUT, NetVLAD at 30 with the
    centres negated, whitening at 33) and net.meta.normalization.averageImage."""
    from scipy.io import savemat

    def cell(*arrays):
        c = np.empty(len(arrays), dtype=object)
        c[:] = list(arrays)
        return c

    layers = np.empty(34, dtype=object)
    for i in range(34):
        layers[i] = {"type": "relu"}
        if f"backbone.{i}.weight" in state:
            w = state[f"backbone.{i}.weight"].permute(2, 3, 1, 0).numpy()
            layers[i] = {"type": "conv", "weights": cell(w, state[f"backbone.{i}.bias"].numpy())}
    layers[30] = {
        "type": "custom",
        "weights": cell(state["netvlad.score_proj.weight"][..., 0].T.numpy(), -state["netvlad.centers"].numpy()),
    }
    if whiten:
        w = state["whiten.weight"].T.numpy()[None, None]
        layers[33] = {"type": "conv", "weights": cell(w, state["whiten.bias"].numpy())}
    savemat(path, {"net": {"layers": layers, "meta": {"normalization": {"averageImage": mean_image}}}})


# smallest released variant of each method; how the authors' file nests its state dict
LOADING_CASES = [
    ("cosplace", {"backbone": "ResNet18", "dim": 32, "resize": 256}, None),  # resize: any size works; keep it fast
    ("eigenplaces", {"backbone": "ResNet18", "dim": 256, "resize": 256}, None),
    ("mixvpr", {"dim": 128}, None),  # README: torch.load(ckpt) is the state dict itself
    ("mixvpr", {"dim": 128}, "state_dict"),  # a full Lightning checkpoint loads too
    ("boq", None, None),
]


@pytest.mark.parametrize("name,conf,nest", LOADING_CASES)
def test_build_loads_saved_weights_and_describes_a_tile(name, conf, nest, tmp_path, monkeypatch, naip_tile):
    torch.manual_seed(0)
    saved = method_class(name)(conf)
    state = saved.state_dict()
    torch.save({nest: state, "epoch": 3} if nest else state, tmp_path / saved.weight_source.filename)
    monkeypatch.setenv("AEROLOC_WEIGHTS_DIR", str(tmp_path))
    monkeypatch.setenv("AEROLOC_OFFLINE", "1")

    model = build_method(name, conf)

    assert not model.training
    loaded = model.state_dict()
    assert loaded.keys() == state.keys()
    assert all(torch.equal(loaded[k], state[k]) for k in state)
    with torch.inference_mode():
        x = model.preprocess(naip_tile)
        assert x.shape[1:] == (model.conf["resize"],) * 2
        desc = model(x[None])
    assert desc.shape == (1, model.dim)
    assert torch.isfinite(desc).all()
    assert desc.norm(dim=1).item() == pytest.approx(1.0, abs=1e-5)


def test_netvlad_loads_the_matconvnet_file_and_describes_a_tile(tmp_path, monkeypatch, naip_tile):
    conf = {"dim": 32768, "resize": 224}  # the raw-VLAD variant: the 4096-d whitening alone is 537 MB
    torch.manual_seed(0)
    state = method_class("netvlad")(conf).state_dict()
    mean = np.array([120.0, 115.0, 100.0], np.float32)
    mean_image = np.zeros((2, 2, 3), np.float32)
    mean_image[0, 0] = mean  # the authors read averageImage[0, 0]
    write_netvlad_mat(tmp_path / "netvlad_Pitts30K_struct.mat", state, whiten=False, mean_image=mean_image)
    monkeypatch.setenv("AEROLOC_WEIGHTS_DIR", str(tmp_path))
    monkeypatch.setenv("AEROLOC_OFFLINE", "1")

    model = build_method("netvlad", conf)

    loaded = model.state_dict()
    assert all(torch.equal(loaded[k], state[k]) for k in state if k != "mean")
    assert model.mean.flatten().tolist() == mean.tolist()
    with torch.inference_mode():
        x = model.preprocess(naip_tile)
        assert x.shape == (3, 224, 224) and x.min() >= 0 and x.max() <= 255
        desc = model(x[None])
    assert desc.shape == (1, 32768)
    assert desc.norm(dim=1).item() == pytest.approx(1.0, abs=1e-5)


def test_netvlad_matconvnet_conversion_with_whitening(tmp_path):
    """Tiny synthetic struct: conv permutation, negated centres, transposed whitening, mean from [0, 0]."""
    rng = np.random.default_rng(0)
    state = {
        "backbone.0.weight": torch.from_numpy(rng.normal(size=(8, 3, 3, 3)).astype(np.float32)),
        "backbone.0.bias": torch.from_numpy(rng.normal(size=8).astype(np.float32)),
        "netvlad.score_proj.weight": torch.from_numpy(rng.normal(size=(4, 8, 1)).astype(np.float32)),
        "netvlad.centers": torch.from_numpy(rng.normal(size=(8, 4)).astype(np.float32)),
        "whiten.weight": torch.from_numpy(rng.normal(size=(6, 32)).astype(np.float32)),
        "whiten.bias": torch.from_numpy(rng.normal(size=6).astype(np.float32)),
    }
    write_netvlad_mat(tmp_path / "tiny.mat", state, whiten=True, mean_image=np.array([[[1.0, 2.0, 3.0]]]))

    converted = state_from_matconvnet(read_matconvnet(tmp_path / "tiny.mat"), [0], whiten=True)

    for key, value in state.items():
        assert torch.equal(converted[key], value), key
    assert converted["mean"].flatten().tolist() == [1.0, 2.0, 3.0]
    without = state_from_matconvnet(read_matconvnet(tmp_path / "tiny.mat"), [0], whiten=False)
    assert "whiten.weight" not in without


def test_netvlad_layer_equals_the_residual_sum():
    """Our matmul form equals the definition sum_n a_k(x_n) (x_n - c_k), intra- then L2-normalised."""
    torch.manual_seed(0)
    layer = NetVLADLayer(input_dim=16, num_clusters=5)
    x = torch.nn.functional.normalize(torch.randn(2, 16, 30), dim=1)
    a = torch.softmax(layer.score_proj(x), dim=1)  # B x K x N
    residuals = x[:, :, None, :] - layer.centers[None, :, :, None]  # B x D x K x N
    expected = (a[:, None] * residuals).sum(-1)
    expected = torch.nn.functional.normalize(torch.nn.functional.normalize(expected, dim=1).flatten(1), dim=1)
    assert torch.allclose(layer(x), expected, atol=1e-6)


# -- failures -----------------------------------------------------------------------------------------

OFFLINE_CASES = [
    ("netvlad", {"dim": 32768}, "https://cvg-data.inf.ethz.ch/hloc/netvlad/Pitts30K_struct.mat"),
    (
        "cosplace",
        {"backbone": "ResNet18", "dim": 32},
        "https://github.com/gmberton/CosPlace/releases/download/v1.0/ResNet18_32_cosplace.pth",
    ),
    (
        "eigenplaces",
        {"backbone": "ResNet18", "dim": 256},
        "https://github.com/gmberton/EigenPlaces/releases/download/v1.0/ResNet18_256_eigenplaces.pth",
    ),
    ("mixvpr", {"dim": 4096}, "https://drive.google.com/file/d/1vuz3PvnR7vxnDDLQrdHJaOA04SQrtk5L/view"),
    ("boq", None, "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/resnet50_16384.pth"),
]


@pytest.mark.parametrize("name,conf,url", OFFLINE_CASES)
def test_missing_weights_offline_names_url_and_target(name, conf, url, tmp_path, monkeypatch):
    (tmp_path / "weights_dir").mkdir()
    monkeypatch.setenv("AEROLOC_OFFLINE", "1")
    monkeypatch.setenv("AEROLOC_WEIGHTS_DIR", str(tmp_path / "weights_dir"))
    monkeypatch.setenv("AEROLOC_CACHE", str(tmp_path / "cache"))
    model = meta_model(name, conf)

    with pytest.raises(WeightsNotFound) as err:
        model.load_weights()

    assert url in str(err.value)
    assert str(cache_dir() / model.weight_source.filename) in str(err.value)
    assert str(cache_dir()).startswith(str(tmp_path / "cache"))


@pytest.fixture(scope="module")
def foreign_checkpoint(tmp_path_factory):
    """A real checkpoint of another model (CosPlace ResNet18-32 keys) to hand to every method."""
    path = tmp_path_factory.mktemp("foreign") / "cosplace_resnet18_32.pth"
    with torch.device("meta"):
        keys = meta_model("cosplace", {"backbone": "ResNet18", "dim": 32}).state_dict()
    torch.save({k: torch.zeros(v.shape, dtype=v.dtype) for k, v in keys.items()}, path)
    return path


@pytest.mark.parametrize(
    "name,conf",
    [
        ("cosplace", {"backbone": "ResNet18", "dim": 64}),  # same keys, FC of another size
        ("eigenplaces", {"backbone": "ResNet50", "dim": 2048}),
        ("mixvpr", {"dim": 128}),
        ("boq", None),
        ("netvlad", {"dim": 32768}),  # a .pth given instead of the .mat
    ],
)
def test_wrong_checkpoint_is_an_aeroloc_error(name, conf, foreign_checkpoint, tmp_path, monkeypatch):
    model = meta_model(name, conf)
    target = tmp_path / model.weight_source.filename
    target.write_bytes(foreign_checkpoint.read_bytes())
    monkeypatch.setenv("AEROLOC_WEIGHTS_DIR", str(tmp_path))

    with pytest.raises(AerolocError, match=r"does not fit|missing|not a MatConvNet|not a readable") as err:
        model.load_weights()
    assert str(target) in str(err.value)
    assert "\n" not in str(err.value)


def test_netvlad_mat_without_the_vlad_layer_is_an_aeroloc_error(tmp_path):
    from scipy.io import savemat

    layers = np.empty(3, dtype=object)
    layers[:] = [{"type": "relu"}] * 3
    savemat(tmp_path / "short.mat", {"net": {"layers": layers}})
    with pytest.raises(AerolocError, match=r"short\.mat"):
        state_from_matconvnet(read_matconvnet(tmp_path / "short.mat"), [0], whiten=False, source=tmp_path / "short.mat")


def test_mixvpr_rejects_input_of_another_size():
    model = meta_model("mixvpr", {"dim": 128})
    with pytest.raises(AerolocError, match="320"):
        model(torch.empty(1, 3, 224, 224, device="meta"))
