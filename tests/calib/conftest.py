import pytest
from calib_testing import ring_rig

from calib.camera import Rig


@pytest.fixture
def rig12() -> Rig:
    """Twelve varied cameras named cam_0 .. cam_11 (numeric and text order differ)."""
    return ring_rig(12)
