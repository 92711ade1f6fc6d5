"""TriplaneDecoder rejects bad settings when built and a BEV latent with a clear message."""

from __future__ import annotations

import pytest
import torch

from t3fast.models.decoder import TriplaneDecoder


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"pe_freqs": 40}, r"pe_freqs must be in \[0, 30\], got 40"),
    ({"pe_freqs": -1}, r"pe_freqs must be in \[0, 30\], got -1"),
    ({"num_classes": 300}, r"num_classes must be in \[1, 256\], got 300"),
])
def test_bad_settings_fail_at_construction(kwargs, message):
    with pytest.raises(ValueError, match=message):
        TriplaneDecoder(in_channels=4, feature_channels=4, hidden=(8,), refine=False, **kwargs)


def test_bev_latent_given_to_a_triplane_decoder():
    decoder = TriplaneDecoder(in_channels=4, feature_channels=4, hidden=(8,), grid=(4, 4, 2), refine=False)
    bev = (torch.zeros(1, 4, 4, 4), None, None)
    with pytest.raises(ValueError, match="BEV-only latent .* given to a triplane decoder; .* bev=True"):
        decoder(bev)
    bev_decoder = TriplaneDecoder(in_channels=4, feature_channels=4, hidden=(8,), grid=(4, 4, 2), refine=False,
                                  bev=True)
    assert bev_decoder(bev).shape == (1, 4, 4, 2, 18)
