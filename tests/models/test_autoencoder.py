"""Triplane encoder/decoder: shapes, the drop-in decoder API, bad input, learning."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from t3fast import TriplaneDecoder, TriplaneEncoder
from t3fast.models import AutoencoderConfig, Triplane, TriplaneAutoencoder
from t3fast.presets import autoencoder_size

TINY = AutoencoderConfig(
    grid=(12, 10, 4),
    embed_dim=8,
    full_res_channels=8,
    full_res_blocks=1,
    half_res_channels=16,
    half_res_blocks=1,
    channels=8,
    decoder_channels=16,
    decoder_hidden=[64, 64],
    pe_freqs=4,
)


def random_labels(batch, grid, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 18, (batch, *grid), generator=g, dtype=torch.uint8)


def test_defaults_build_the_paper_model_for_occ3d():
    labels = random_labels(1, (200, 200, 16))
    triplane = TriplaneEncoder()(labels)
    assert [tuple(p.shape) for p in triplane] == [(1, 8, 100, 100), (1, 8, 100, 16), (1, 8, 100, 16)]
    assert triplane.numel_per_sample() == 105_600
    assert all(p.abs().max() < 1 for p in triplane)  # bounded latent
    out = TriplaneDecoder().predict(triplane)
    assert out.shape == (1, 200, 200, 16) and out.dtype == torch.uint8


@pytest.mark.parametrize("name", ["small", "small-bev"])
def test_named_configs_shapes(name):
    cfg = dataclasses.replace(autoencoder_size(name), grid=(20, 16, 4))
    model = TriplaneAutoencoder(cfg)
    labels = random_labels(2, cfg.grid)
    triplane = model.encode(labels)
    if cfg.latent == "bev":
        assert triplane.xz is None and triplane.yz is None and triplane.xy.shape == (2, cfg.channels, 10, 8)
    else:
        assert triplane.xz.shape == (2, cfg.channels, 10, 4)
    points = torch.rand(2, 37, 3) * 2 - 1
    assert model.decoder(triplane, points).shape == (2, 37, 18)
    assert model(labels).shape == (2, *cfg.grid, 18)
    assert model.reconstruct(labels).shape == (2, *cfg.grid)


def test_bev_latent_matches_triplane_size():
    tri, bev = autoencoder_size("small"), autoencoder_size("small-bev")
    x, y, z = tri.plane_shape
    tri_size = tri.channels * (x * y + x * z + y * z)
    assert bev.latent == "bev" and abs(bev.channels * x * y - tri_size) / tri_size < 0.05


def test_decoder_state_dict_is_plain_and_round_trips():
    torch.manual_seed(0)
    decoder = TriplaneDecoder(in_channels=4, feature_channels=8, hidden=[16], grid=(6, 6, 4), pe_freqs=2)
    keys = set(decoder.state_dict())
    assert {"mlp.0.weight", "mlp.0.bias", "mlp.1.weight", "refiners.0.body.0.weight"} <= keys
    clone = TriplaneDecoder(in_channels=4, feature_channels=8, hidden=[16], grid=(6, 6, 4), pe_freqs=2)
    clone.load_state_dict(decoder.state_dict())
    triplane = Triplane(torch.randn(1, 4, 3, 3), torch.randn(1, 4, 3, 2), torch.randn(1, 4, 3, 2))
    assert torch.equal(decoder(triplane), clone(triplane))
    assert torch.equal(decoder.predict(triplane), decoder(triplane).argmax(-1).to(torch.uint8))


def test_fused_and_reference_backends_agree():
    torch.manual_seed(0)
    fused = TriplaneDecoder(in_channels=4, feature_channels=8, hidden=[32, 32], grid=(8, 6, 4), pe_freqs=3)
    ref = TriplaneDecoder(in_channels=4, feature_channels=8, hidden=[32, 32], grid=(8, 6, 4), pe_freqs=3,
                          backend="reference")
    ref.load_state_dict(fused.state_dict())
    triplane = [torch.randn(2, 4, 4, 3), torch.randn(2, 4, 4, 4), torch.randn(2, 4, 3, 4)]
    points = torch.rand(2, 50, 3) * 2 - 1
    for query in (None, points):
        a, b = fused(triplane, query), ref(triplane, query)
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
        a.square().sum().backward()
        b.square().sum().backward()
    for (name, p), q in zip(fused.named_parameters(), ref.parameters()):
        torch.testing.assert_close(p.grad, q.grad, rtol=1e-3, atol=1e-4, msg=name)


@pytest.mark.parametrize("label_dtype", [torch.uint8, torch.int16, torch.int64])
def test_encoder_backends_agree_forward_and_backward(label_dtype):
    """The stem as one label_conv3d (fused) and as the embedding and convolution it is."""
    torch.manual_seed(0)
    fused = TriplaneEncoder(TINY)
    ref = TriplaneEncoder(TINY, backend="reference")
    ref.load_state_dict(fused.state_dict())
    labels = random_labels(2, TINY.grid).to(label_dtype)
    labels[0, 0, 0, 0] = 255  # ignore: encoded as free
    a, b = fused(labels), ref(labels)
    for p, q in zip(a, b):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-5)
    sum(p.square().sum() for p in a).backward()
    sum(q.square().sum() for q in b).backward()
    for (name, p), q in zip(fused.named_parameters(), ref.parameters()):
        torch.testing.assert_close(p.grad, q.grad, rtol=1e-4, atol=1e-3, msg=name)  # sums of ~1e3 terms up to 40


def test_encoder_is_accurate_on_a_full_occ3d_frame():
    """float32 planes of a 200 x 200 x 16 frame within 1e-4 of float64's. The CPU GroupNorm
    loses precision on a channels-last input over 640 k voxels: an embedding permuted into the
    stem left its output channels-last and moved planes by up to 0.14."""
    from t3fast.data.synthetic import SyntheticDriving
    from t3fast.pretrained import load_world_model

    encoder = load_world_model("wm-small").encoder
    frame = SyntheticDriving("val", 1, 20, stride=9)[0].occ[None, -1]
    with torch.no_grad():
        single = encoder(frame)
        double = encoder.double()(frame)
    for p, q in zip(single, double):
        torch.testing.assert_close(p.double(), q, rtol=0, atol=1e-4)


def test_encoder_rejects_unknown_backend():
    with pytest.raises(ValueError, match="backend must be 'fused' or 'reference', got 'cuda'"):
        TriplaneEncoder(TINY, backend="cuda")


@pytest.mark.parametrize(
    "labels, pattern",
    [
        (torch.zeros(1, 12, 10, 5, dtype=torch.uint8), r"labels must have shape \[B, 12, 10, 4\], got \[1, 12, 10, 5"),
        (torch.zeros(1, 12, 10, 4), r"labels must be an integer tensor of class ids, got torch.float32"),
        (torch.full((1, 12, 10, 4), 18, dtype=torch.uint8), r"class ids in 0..17 or 255 \(ignore\), got \[18\]"),
        (torch.full((1, 12, 10, 4), -1, dtype=torch.int64), r"got \[-1\]"),
    ],
)
def test_encoder_rejects_bad_labels(labels, pattern):
    with pytest.raises(ValueError, match=pattern):
        TriplaneEncoder(TINY)(labels)


def test_ignore_label_is_accepted_as_free():
    labels = random_labels(1, TINY.grid)
    labels[0, 0, 0, 0] = 255
    encoder = TriplaneEncoder(TINY)
    with_ignore = encoder(labels)
    labels[0, 0, 0, 0] = 17
    for a, b in zip(with_ignore, encoder(labels)):
        assert torch.equal(a, b)


def test_tiny_model_overfits_one_batch():
    """The gradient path through the fused ops is right: a tiny autoencoder memorises a batch."""
    torch.manual_seed(0)
    cfg = dataclasses.replace(TINY, grid=(8, 8, 4))
    labels = random_labels(1, cfg.grid, seed=3)
    model = TriplaneAutoencoder(cfg)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(200):
        logits = model(labels)
        loss = torch.nn.functional.cross_entropy(logits.reshape(-1, 18), labels.reshape(-1).long())
        opt.zero_grad()
        loss.backward()
        opt.step()
    accuracy = (model.reconstruct(labels) == labels).float().mean().item()
    assert accuracy > 0.99, accuracy
