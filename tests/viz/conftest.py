"""A real synthetic window shared by the viewer tests (building it takes a couple of seconds)."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="session")
def synthetic_window() -> dict[str, np.ndarray]:
    """One synthetic test window: ``occ`` uint8 ``[11, 200, 200, 16]`` (5 past, 6 future),
    ``mask`` bool of the same shape, ``trajectory`` ``[6, 2]``."""
    from t3fast.data.synthetic import SyntheticDriving

    sample = SyntheticDriving("test", 1, stride=8)[0]
    return {"occ": sample.occ.numpy(), "mask": sample.mask_camera.numpy(), "trajectory": sample.trajectory.numpy()}
