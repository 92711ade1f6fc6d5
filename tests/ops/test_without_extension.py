"""Without the compiled extension the ops, and the models on them, run through the references.

The extension is hidden in a fresh interpreter by ``sys.modules["t3fast._C"] = None``, which
makes ``from t3fast import _C`` raise ImportError as a missing build does.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import torch

import t3fast

ROOT = Path(__file__).resolve().parents[2]

HIDE_EXTENSION = 'import sys; sys.modules["t3fast._C"] = None\n'

FALLBACK_SCRIPT = """
import warnings

warnings.simplefilter("always")
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    import torch

    import t3fast
    from t3fast.ops import reference
    from t3fast.models.config import AutoencoderConfig
    from tests.ops.test_triplane_decode import make_inputs, random_points

    info = t3fast.build_info()
    assert info["compiled"] is False and info["cpu"] is False and info["cuda"] is False, info
    assert "t3fast._C cannot be imported" in info["reason"], info
    assert "pip install --no-build-isolation -e ." in info["reason"], info

    planes, weights, biases = make_inputs(2, 4, (5, 6, 3), [8], 1, 5)
    for query in ({"grid": (4, 3, 2)}, {"points": random_points(2, 7)}):
        for argmax in (False, True):
            got = t3fast.triplane_decode(*planes, weights, biases, pe_freqs=1, argmax=argmax, **query)
            want = reference.triplane_decode(*planes, weights, biases, pe_freqs=1, argmax=argmax, **query)
            assert got.dtype == (torch.uint8 if argmax else torch.float32), got.dtype
            assert torch.equal(got, want), (query, argmax)
    live = torch.tensor([3, 0])
    got = t3fast.triplane_decode(*planes, weights, biases, pe_freqs=1, argmax=True, points=random_points(2, 7),
                                 live=live)
    assert got[0, 3:].eq(0).all() and got[1].eq(0).all(), got

    volume = torch.randn(2, 3, 4, 5, 6)
    for got, want in zip(t3fast.axis_pool(volume), reference.axis_pool(volume)):
        assert torch.equal(got, want)
    delta, prev, weight, bias = torch.randn(2, 4, 5, 6), torch.randn(2, 3, 5, 6), torch.randn(4, 3), torch.randn(4)
    assert torch.equal(t3fast.delta_fuse(delta, prev, weight, bias), reference.delta_fuse(delta, prev, weight, bias))
    present, previous = torch.randn(2, 3, 5, 4), torch.randn(2, 3, 5, 4)
    assert torch.equal(t3fast.ops.matching_costs(present, previous, 2), reference.matching_costs(present, previous, 2))
    try:
        t3fast.ops.matching_costs(present, previous[:, :2], 2)
    except RuntimeError as exc:
        assert "t3fast.matching_costs: previous must have the shape of present [2, 3, 5, 4]" in str(exc), exc
    else:
        raise AssertionError("a channel mismatch was accepted")
    x, w, b, r = torch.randn(2, 4, 5, 3), torch.randn(4), torch.randn(4), torch.randn(2, 4, 5, 3)
    assert torch.equal(t3fast.ops.group_norm_silu(x, w, b, 2, 1e-5, r), reference.group_norm_silu(x, w, b, 2, 1e-5, r))
    try:
        t3fast.ops.group_norm_silu(x, w, b, 3)
    except RuntimeError as exc:
        assert "t3fast.group_norm_silu: groups must be a positive divisor of the 4 channels, got 3" in str(exc), exc
    else:
        raise AssertionError("groups not dividing the channels were accepted")

    # a model on the ops, against the same model on the reference decoder
    torch.manual_seed(0)
    cfg = AutoencoderConfig(grid=(8, 8, 4), embed_dim=4, full_res_channels=4, full_res_blocks=0,
                            half_res_channels=4, half_res_blocks=1, channels=4, decoder_channels=8,
                            decoder_hidden=[16])
    model = t3fast.TriplaneAutoencoder(cfg).eval()
    ref_model = t3fast.TriplaneAutoencoder(cfg, decoder_backend="reference").eval()
    ref_model.load_state_dict(model.state_dict())
    labels = torch.randint(0, cfg.num_classes, (1, 8, 8, 4))
    logits = model(labels)
    assert logits.shape == (1, 8, 8, 4, cfg.num_classes), logits.shape
    torch.testing.assert_close(logits, ref_model(labels))
    logits.sum().backward()  # trains through the references
    assert model.decoder.mlp[0].weight.grad is not None
    assert torch.equal(model.reconstruct(labels), ref_model(labels).argmax(-1).to(torch.uint8))

    try:
        t3fast.triplane_decode(planes[0], planes[1][:, :3], planes[2], weights, biases, grid=(2, 2, 2), pe_freqs=1)
    except RuntimeError as exc:
        assert "t3fast.triplane_decode: xz.shape[1] (channels, as xy) must be 4, got 3" in str(exc), exc
    else:
        raise AssertionError("a channel mismatch was accepted")

messages = [str(w.message) for w in caught if "t3fast" in str(w.message)]
assert len(messages) == 1, messages
assert "t3fast._C cannot be imported" in messages[0], messages
assert "pip install --no-build-isolation -e ." in messages[0], messages
print("fallback ok")
"""


def _run(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.pathsep.join(
        p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=300)


def test_ops_and_models_fall_back_to_the_references():
    result = _run(HIDE_EXTENSION + textwrap.dedent(FALLBACK_SCRIPT))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "fallback ok" in result.stdout


def test_fallback_rejects_bad_arguments_as_the_kernels_do():
    """The argument tests of the compiled ops pass on the fallback too, with the same messages
    (less the one that calls a backward op of the extension directly)."""
    code = HIDE_EXTENSION + (
        "import pytest\n"
        "sys.exit(pytest.main(['-q', '-p', 'no:cacheprovider', '-W', 'ignore::RuntimeWarning',"
        " 'tests/ops/test_bad_input.py', 'tests/ops/test_decode_limits.py', '-k', 'not backward_op']))\n"
    )
    result = _run(code)
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_build_reports_itself_compiled():
    info = t3fast.build_info()
    assert info["compiled"] is True
    assert "reason" not in info
    assert hasattr(torch.ops.t3fast, "triplane_decode")


def test_an_extension_built_for_another_torch_is_not_used():
    code = """
import warnings

import torch

torch.__version__ = "1.0.0"  # the extension was built against the installed torch
warnings.simplefilter("ignore")
import t3fast
from t3fast.ops import reference

info = t3fast.build_info()
assert not info["compiled"], info
assert "was compiled against torch" in info["reason"] and "torch 1.0.0 is running" in info["reason"], info
volume = torch.randn(1, 2, 3, 4, 5)
assert all(torch.equal(a, b) for a, b in zip(t3fast.axis_pool(volume), reference.axis_pool(volume)))
"""
    result = _run(code)
    assert result.returncode == 0, result.stdout + result.stderr
