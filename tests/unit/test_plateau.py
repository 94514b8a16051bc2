"""agent.telemetry.PlateauRule: a flat loss that is still high is a warning; a low or falling one is not."""

from agent.telemetry import PlateauRule


def test_flat_and_high_is_a_plateau():
    rule = PlateauRule(window=4, rel_change=0.03, above_loss=0.03)
    assert rule.is_flat([0.2, 0.12, 0.088, 0.087, 0.089, 0.088])
    assert rule.is_flat([0.012, 0.0121, 0.0119, 0.012, 0.012])  # low, but never fell: learning nothing


def test_falling_low_or_too_short_is_not():
    rule = PlateauRule(window=4, rel_change=0.03, above_loss=0.03)
    assert not rule.is_flat([0.09, 0.08, 0.07, 0.06])  # still learning
    assert not rule.is_flat([0.03, 0.005, 0.005, 0.005, 0.005])  # converged: ~23 dB
    assert not rule.is_flat([0.088, 0.088, 0.088])  # fewer rounds than the window
