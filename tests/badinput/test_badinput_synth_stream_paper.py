"""``minegeo synth OUT --stream ... --stream-network paper-...``: an unknown paper path, options the paper
world does not simulate, and a duration longer than the path are one line, exit 2, nothing written."""

from __future__ import annotations

import pytest
from _contract import assert_user_error

CASES = {
    "unknown_paper_network": (["--stream-network", "paper-circle"], "paper-ring"),
    "stations_on_paper": (["--stream-network", "paper-ring", "--station-spacing-m", "20"], "stations"),
    "width_on_paper": (["--stream-network", "paper-ramp", "--drift-width-m", "3"], "width"),
    # the ring lasts ~43 s for the vehicle: the message says how long and what fits
    "longer_than_the_path": (["--stream-network", "paper-ring", "--duration-s", "60"], "lasts"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_paper_stream(case, tmp_path, capsys):
    argv, expect = CASES[case]
    out = tmp_path / "s"
    assert_user_error("synth", [out, "--stream", "vehicle", *argv], capsys, outputs=[out], expect=expect)
