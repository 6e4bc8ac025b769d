"""Learning-rate schedules: warm-up, then cosine, linear or constant."""

import pytest
import torch

from crestereo_pp.training.schedule import build_scheduler, learning_rate_factor, set_horizon


def test_warmup_ramps_linearly_to_the_peak():
    # 10 % of 100 steps = 10 warm-up steps
    assert [learning_rate_factor(s, 100, "one-cycle", 0.1) for s in (0, 4, 9)] == pytest.approx([0.1, 0.5, 1.0])


@pytest.mark.parametrize(
    ("schedule", "middle", "end"), [("one-cycle", 0.5, 0.0), ("linear", 0.5, 0.0), ("constant", 1.0, 1.0)]
)
def test_decay_after_warmup(schedule, middle, end):
    # no warm-up, 100 steps: step 50 is half-way; the factor reaches `end` after the last step
    assert learning_rate_factor(50, 100, schedule, 0.0) == pytest.approx(middle)
    assert learning_rate_factor(100, 100, schedule, 0.0) == pytest.approx(end, abs=1e-12)


def test_one_cycle_is_a_half_cosine():
    assert learning_rate_factor(25, 100, "one-cycle", 0.0) == pytest.approx(0.5 * (1 + 2**-0.5))


def test_scheduler_sets_the_optimiser_lr_step_by_step():
    weight = torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.AdamW([weight], lr=1.0)
    scheduler = build_scheduler(optimizer, 4, "linear", 0.5)  # 2 warm-up steps
    lrs = []
    for _ in range(4):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert lrs == pytest.approx([0.5, 1.0, 1.0, 0.5])


def test_flat_decay_holds_the_peak_then_decays_linearly_over_the_last_steps():
    factors = [learning_rate_factor(s, 100, "flat-decay", 0.0, decay_steps=20) for s in (0, 79, 80, 90, 99, 100)]
    assert factors == pytest.approx([1.0, 1.0, 1.0, 0.5, 0.05, 0.0])


def test_a_new_horizon_takes_effect_from_the_step_the_scheduler_stands_at():
    weight = torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.AdamW([weight], lr=1.0)
    scheduler = build_scheduler(optimizer, 100, "flat-decay", 0.0, decay_steps=20)
    for _ in range(10):
        optimizer.step()
        scheduler.step()
    set_horizon(scheduler, 14, "flat-decay", 0.0, decay_steps=4)  # the decay now begins at step 10
    lrs = []
    for _ in range(4):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert lrs == pytest.approx([1.0, 0.75, 0.5, 0.25])
