"""Standalone scores (device_runtime/standalone.py): the device interpolates exactly the
host's scores from the table in the image, and refuses a bad table in one line. The
delta-coded table and the RD packets: test_rd_packets.py."""

from __future__ import annotations

import numpy as np
import pytest

from device_runtime.orbit import canonical_view
from device_runtime.standalone import STANDALONE_SECTION, StandaloneScores, standalone_table
from protocol.errors import ImageFormatError
from protocol.image import read_image


def test_standalone_scores_match_the_host_and_bad_tables_are_refused(model_path, model):
    image = read_image(model_path)
    standalone = StandaloneScores(image)
    for view in [(0.0, 0.0), (33.3, 12.0), (359.0, -40.0), (181.0, 89.0)]:
        view = canonical_view(*view)
        np.testing.assert_array_equal(standalone.scores(*view), model.quantized_scores(*view))
    table, step = standalone_table(image)
    assert table.dtype == np.int16 and step == model.score_step
    image.sections[STANDALONE_SECTION] = table.astype(np.float32)
    with pytest.raises(ImageFormatError, match="int16/int32"):
        standalone_table(image)
    image.sections[STANDALONE_SECTION] = table[:, :-1]
    with pytest.raises(ImageFormatError, match="shape"):
        standalone_table(image)
    image.sections[STANDALONE_SECTION] = table
    image.score_quantization = {"step": 1.0, "table_step": -1}
    with pytest.raises(ImageFormatError, match="table_step"):
        standalone_table(image)
    del image.sections[STANDALONE_SECTION]
    with pytest.raises(ImageFormatError, match="fit --standalone"):
        StandaloneScores(image)
