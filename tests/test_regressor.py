"""The regressor model: presets, normalisation, bf16 precision, training on a toy problem."""

import numpy as np
import pytest
import torch

from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig, resolve_device, train_regressor


@pytest.mark.parametrize("arch, dim, low, high", [("paper", 256, 2.2e6, 2.4e6),
                                                  ("tiny", 256, 0.6e6, 0.8e6)])
def test_paper_presets_have_the_published_sizes(arch, dim, low, high):
    n = SceneCoordinateRegressor(RegressorConfig.preset(arch, dim)).num_parameters()
    assert low < n < high


def test_unknown_preset():
    with pytest.raises(ValueError, match="unknown architecture"):
        RegressorConfig.preset("huge", 128)


def _toy(n_points=300, views=6, dim=128, seed=0):
    """Each 3D point is seen as `views` noisy copies of one random unit descriptor."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(n_points, dim))
    desc = np.repeat(centres, views, 0) + 0.3 * rng.normal(size=(n_points * views, dim))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    points = np.repeat(rng.uniform(-2, 2, (n_points, 3)), views, 0)
    return desc.astype(np.float32), points.astype(np.float32)


@pytest.mark.parametrize("head", ["regression", "clusters"])
def test_training_fits_and_generalises_to_new_observations(head):
    desc, points = _toy()
    model = SceneCoordinateRegressor(RegressorConfig(128, (512, 256, 128), head=head,
                                                     n_clusters=64))
    stats = train_regressor(model, desc, points, TrainConfig(epochs=60, batch_size=256),
                            "cpu", progress=False)
    assert stats["final_loss_m"] < 0.2
    new_desc, new_points = _toy(seed=0)  # same points, fresh observation noise
    rng = np.random.default_rng(1)
    noisy = new_desc + 0.02 * rng.normal(size=new_desc.shape).astype(np.float32)
    with torch.no_grad():
        err = np.linalg.norm(model(torch.as_tensor(noisy)).numpy() - new_points, axis=1)
    assert np.median(err) < 0.15


@pytest.mark.parametrize("head", ["regression", "clusters"])
def test_bf16_inference_keeps_centimetre_precision(head):
    """The output layer runs in float32 even under bf16 autocast."""
    model = SceneCoordinateRegressor(RegressorConfig(128, (256, 128), head=head,
                                                     n_clusters=32)).eval()
    model.centres.normal_()
    x = torch.randn(512, 128)
    model.out_mean.fill_(30.0)  # a map far from the origin
    with torch.no_grad():
        ref = model(x)
        with torch.autocast("cpu", torch.bfloat16):
            fast = model(x)
    assert fast.dtype == torch.float32
    assert (fast - ref).norm(dim=1).median() < 0.05 * ref.sub(30).norm(dim=1).median()


def test_clusters_partition_the_training_points():
    model = SceneCoordinateRegressor(RegressorConfig(128, (64,), head="clusters", n_clusters=16))
    points = torch.randn(2000, 3)
    assign = model.set_clusters(points, torch.Generator().manual_seed(0))
    nearest = torch.cdist(points, model.centres).argmin(1)
    assert torch.equal(assign, nearest)
    assert len(assign.unique()) == 16
    offset = (points - model.centres[assign]).norm(dim=1).mean()
    assert torch.isclose(model.offset_scale, offset)


def test_clusters_with_fewer_points_than_regions():
    model = SceneCoordinateRegressor(RegressorConfig(128, (64,), head="clusters", n_clusters=16))
    assign = model.set_clusters(torch.randn(5, 3), torch.Generator().manual_seed(0))
    assert len(assign) == 5 and torch.isfinite(model.centres).all()


def test_cluster_head_confidence_is_a_probability():
    desc, points = _toy(n_points=100)
    model = SceneCoordinateRegressor(RegressorConfig(128, (256, 128), head="clusters",
                                                     n_clusters=32))
    train_regressor(model, desc, points, TrainConfig(epochs=30, batch_size=256), "cpu",
                    progress=False)
    with torch.no_grad():
        _, seen = model.predict(torch.as_tensor(desc))
        _, unseen = model.predict(torch.as_tensor(_toy(n_points=100, seed=5)[0]))
    assert ((seen >= 0) & (seen <= 1)).all()
    assert seen.median() > unseen.median()  # training descriptors are the confident ones


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_the_seed_alone_fixes_the_trained_model(precision):
    """Two trainings with one seed end on the same weights, whatever state torch's global
    generator was in when each model was built; another seed gives another model. Two torch
    threads and full batches: with the region head's offset rows gathered by advanced
    indexing, whose backward adds rows from both threads in whichever order they come, the
    weights differed from run to run on a 2-core Xeon."""
    if precision == "bf16" and not torch.backends.mkldnn.is_available():
        pytest.skip("no oneDNN for bf16 on this CPU build")
    desc, points = _toy(n_points=700)
    config = RegressorConfig(128, (256, 128), head="clusters", n_clusters=16)
    threads = torch.get_num_threads()

    def trained(seed, global_seed):
        torch.manual_seed(global_seed)  # another caller's use of the global generator
        model = SceneCoordinateRegressor(config)
        train_regressor(model, desc, points, TrainConfig(epochs=3, batch_size=1024, seed=seed,
                                                         precision=precision),
                        "cpu", progress=False)
        return model.state_dict()

    torch.set_num_threads(2)
    try:
        a, b, other = trained(0, 1), trained(0, 2), trained(1, 1)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["mlp.2.weight"], other["mlp.2.weight"])


def test_unknown_head():
    with pytest.raises(ValueError, match="unknown head"):
        SceneCoordinateRegressor(RegressorConfig(128, (64,), head="mixture"))


def test_prototype_initialisation_uses_training_descriptors():
    desc, points = _toy(n_points=50)
    model = SceneCoordinateRegressor(RegressorConfig(128, (64, 32), prototype_threshold=0.5))
    x = torch.as_tensor(desc)
    model.set_normalisation(x, torch.as_tensor(points))
    xn = model.normalise_input(x)
    model.init_prototypes(xn, torch.Generator().manual_seed(0))
    act = torch.relu(model.mlp[0](xn))
    # sparse: each descriptor fires few units, and every unit fires for its own prototype
    assert (act > 0).float().mean() < 0.3
    assert ((act > 0).sum(0) > 0).all()


def test_device_resolution():
    assert resolve_device("cpu").type == "cpu"
    if not torch.cuda.is_available():
        assert resolve_device("auto").type == "cpu"
        with pytest.raises(ValueError, match="CUDA"):
            resolve_device("cuda")


def test_weight_averaging_ends_on_the_mean_of_the_last_epochs_weights():
    """average_tail=0.5 of 6 epochs: the model ends on the mean of its weights after epochs
    3, 4 and 5, each seen by on_epoch_end before averaging replaces them."""
    desc, points = _toy(n_points=100)
    model = SceneCoordinateRegressor(RegressorConfig(128, (64, 32), head="clusters",
                                                     n_clusters=16))
    seen = {}

    def snapshot(epoch, loss_m):
        assert loss_m > 0
        seen[epoch] = {k: v.clone() for k, v in model.named_parameters()}

    stats = train_regressor(model, desc, points,
                            TrainConfig(epochs=6, batch_size=256, average_tail=0.5,
                                        precision="fp32"),
                            "cpu", progress=False, on_epoch_end=snapshot)
    assert sorted(seen) == list(range(6)) and stats["averaged_epochs"] == 3
    for name, p in model.named_parameters():
        mean = sum(seen[e][name] for e in (3, 4, 5)) / 3
        assert torch.allclose(p, mean, atol=1e-6), name
        assert not torch.allclose(p, seen[5][name], atol=1e-4), name  # the weights did move
