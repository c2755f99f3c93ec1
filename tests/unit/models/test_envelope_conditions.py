"""``--conditions envelope:N:SEED``: seeded conditions across the whole envelope (issue 24)."""

from __future__ import annotations

import numpy as np
import pytest

from models.envelope_conditions import ENVELOPE_FRACTION, envelope_conditions, parse_envelope_spec
from models.errors import ModelInputError
from models.robots import load_robot

ROBOT = load_robot("ur5_paper")


def test_envelope_conditions_are_seeded_varied_and_inside_80_percent_of_the_limits() -> None:
    conditions = envelope_conditions(ROBOT, 30, 11)
    assert conditions == envelope_conditions(ROBOT, 30, 11)
    assert conditions != envelope_conditions(ROBOT, 30, 12)
    assert {c.shape for c in conditions} == {"raised_sine", "sine", "constant"}
    assert len({c.disturbance.time_s for c in conditions if c.disturbance}) > 1
    position = np.minimum(np.asarray(ROBOT.position_limit_rad), np.pi) * ENVELOPE_FRACTION
    velocity = np.asarray(ROBOT.velocity_limit_rad_s) * ENVELOPE_FRACTION
    reach = np.zeros(ROBOT.n_joints)
    for c in conditions:
        low, high, fastest = c.extrema()
        assert np.all(low >= -position - 1e-9) and np.all(high <= position + 1e-9)
        assert np.all(fastest <= velocity + 1e-9)
        reach = np.maximum(reach, np.maximum(np.abs(low), np.abs(high)))
    assert np.all(reach > 0.5 * position)  # offsets reach far from home on every joint


@pytest.mark.parametrize("text", ["envelope:0:1", "envelope:x:1", "envelope:3", "envelope:3:1:2"])
def test_a_bad_envelope_spec_is_one_line(text: str) -> None:
    with pytest.raises(ModelInputError, match="expected envelope:COUNT:SEED"):
        parse_envelope_spec(text)
    assert parse_envelope_spec("conditions.yaml") is None
