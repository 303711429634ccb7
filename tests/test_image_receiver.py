"""What the device accepts as an image (device_runtime/image_receiver.py): the RAM an image
declares it needs, and the one-line reason an image would not load. The IMAGE_* handlers
run in every provisioning test (test_provision.py, test_device_fuzz.py,
test_boot_fallback.py)."""

from __future__ import annotations

import pytest
from provision_helpers import KEY, OTHER_KEY, make_image

from device_runtime.errors import BudgetError
from device_runtime.image_receiver import image_problem, read_device_image, required_ram_bytes
from protocol.image import read_manifest


def test_ram_grows_with_the_image_and_bounds_what_loads(tmp_path):
    small, large = tmp_path / "small.ecs", tmp_path / "large.ecs"
    make_image(small, size_bytes=50_000)
    make_image(large, size_bytes=400_000)
    with open(small, "rb") as handle:
        need = required_ram_bytes(read_manifest(handle))
    with open(large, "rb") as handle:
        assert required_ram_bytes(read_manifest(handle)) > need
    with open(small, "rb") as handle:
        assert read_device_image(handle, key=KEY, ram_budget_bytes=need) is not None
    with open(small, "rb") as handle, pytest.raises(BudgetError, match=f"budget is {need - 1}"):
        read_device_image(handle, key=KEY, ram_budget_bytes=need - 1)


def test_image_problem_is_none_or_one_line(tmp_path):
    path = tmp_path / "image.ecs"
    make_image(path)
    with open(path, "rb") as handle:
        assert image_problem(handle, key=KEY, ram_budget_bytes=1 << 30) is None
    for key, budget in ((OTHER_KEY, 1 << 30), (KEY, 1000)):
        with open(path, "rb") as handle:
            problem = image_problem(handle, key=key, ram_budget_bytes=budget)
        assert problem and "\n" not in problem
