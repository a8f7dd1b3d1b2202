import math
import re

import pytest
import torch

from voxe_core.schedule import AUTHORS_FLOOR, PAPER_FLOOR, TimestepSchedule


@pytest.mark.parametrize(
    "iteration, k",
    [  # the appendix's k_i = k_(i-1)·0.75 when i >= 4000 and i % 600 == 0, on the authors' 1-based step count
        (0, 0.98),
        (4198, 0.98),  # step 4199
        (4199, 0.98 * 0.75),  # step 4200: the first multiple of 600 from i_start (4000 is not one)
        (4798, 0.98 * 0.75),
        (4799, 0.98 * 0.75**2),
        (5399, 0.98 * 0.75**3),
        (5998, 0.98 * 0.75**3),  # 0.413 > 0.35
        (5999, 0.35),  # 0.98 * 0.75**4 = 0.310 -> floor
        (20000, 0.35),
    ],
)
def test_paper_schedule(iteration, k):
    assert TimestepSchedule().max_fraction(iteration) == pytest.approx(k, abs=1e-12)


def test_paper_rule_literally():
    """k_i by the appendix's recursion, step by step (1-based), for both presets' (i_start, f_a): the closed form
    agrees at every iteration, an i_start that is a multiple of f_a included."""
    for i_start, every in ((4000, 600), (3000, 400), (3600, 600), (0, 600), (1, 600)):
        schedule, k = TimestepSchedule(i_start=i_start, every=every), 0.98
        for step in range(1, 9001):
            if step >= i_start and step % every == 0:
                k *= 0.75
            assert schedule.max_fraction(step - 1) == pytest.approx(max(k, 0.35), abs=1e-12), (i_start, step)


def test_authors_floor():
    s = TimestepSchedule.authors()
    assert AUTHORS_FLOOR == 0.22 and s.floor == 0.22 and PAPER_FLOOR == 0.35
    assert s.max_fraction(5999) == pytest.approx(0.98 * 0.75**4)  # 0.310, above 0.22
    assert s.max_fraction(6599) == pytest.approx(0.98 * 0.75**5)  # 0.233
    assert s.max_fraction(7199) == pytest.approx(0.22)  # 0.174 -> floor
    assert s.max_fraction(20000) == pytest.approx(0.22)
    assert TimestepSchedule(floor=AUTHORS_FLOOR).max_fraction(20000) == pytest.approx(0.22)


def test_schedule_is_monotone_non_increasing():
    s = TimestepSchedule()
    values = [s.max_fraction(i) for i in range(0, 9000, 50)]
    assert all(b <= a for a, b in zip(values, values[1:]))


@pytest.mark.parametrize("iteration, lo, hi", [(0, 20, 980), (4199, 20, 735), (4799, 20, 551), (20000, 20, 350)])
def test_samples_within_range(iteration, lo, hi):
    s = TimestepSchedule()
    assert s.bounds(iteration) == (lo, hi)
    t = s.sample(iteration, 20000, generator=torch.Generator().manual_seed(0))
    assert t.dtype == torch.long and t.shape == (20000,)
    assert int(t.min()) == lo and int(t.max()) == hi  # both ends reachable, nothing outside
    # roughly uniform: mean near the middle
    assert float(t.float().mean()) == pytest.approx((lo + hi) / 2, rel=0.02)


def test_a_schedule_starting_at_k_one_stops_at_the_last_time_step():
    """k0 = 1 is allowed, and floor(k·T) = T is a time step the scheduler does not have: the range ends at T − 1."""
    s = TimestepSchedule(k0=1.0)
    assert s.bounds(0) == (20, 999) and s.bounds(0, num_train_timesteps=100) == (2, 99)
    assert int(s.sample(0, 20000, generator=torch.Generator().manual_seed(0)).max()) == 999


def test_sample_reproducible_and_scaled_by_T():
    s = TimestepSchedule()
    a = s.sample(0, 8, generator=torch.Generator().manual_seed(1))
    b = s.sample(0, 8, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a, b)
    t = s.sample(0, 5000, num_train_timesteps=100, generator=torch.Generator().manual_seed(2))
    assert int(t.min()) >= 2 and int(t.max()) <= 98


def test_invalid_schedules_rejected():
    with pytest.raises(ValueError, match=r"^need 0 <= t_min < floor <= k0 <= 1, got t_min=0\.02, floor=0\.01, k0=0\.98$"):
        TimestepSchedule(floor=0.01)
    with pytest.raises(ValueError, match=r"^every must be >= 1, got 0$"):
        TimestepSchedule(every=0)
    with pytest.raises(ValueError, match=r"^iteration must be >= 0, got -1$"):
        TimestepSchedule().max_fraction(-1)


@pytest.mark.parametrize("name", ["i_start", "every"])
@pytest.mark.parametrize("value", [math.nan, 600.5, True])
def test_an_annealing_step_that_is_no_whole_number_is_refused_by_name(name, value):
    """A NaN i_start had annealed to the floor from iteration 0 (max(floor, NaN) is the floor), silently."""
    with pytest.raises(ValueError, match=rf"^{name} takes whole numbers \(iterations\), got {re.escape(repr(value))}$"):
        TimestepSchedule(**{name: value})
    assert TimestepSchedule(**{name: 600}).max_fraction(0) == 0.98


@pytest.mark.parametrize("name, value", [("t_min", "0.02"), ("floor", None), ("factor", "0.75"), ("factor", True),
                                         ("k0", True), ("t_min", False)])
def test_an_annealing_fraction_that_is_no_number_is_refused_by_name(name, value):
    """Regression: a string or None had been a TypeError naming no setting ("'<' not supported between instances of
    'float' and 'str'"), and True or False had run as 1 or 0 (factor=True: no annealing at all)."""
    with pytest.raises(ValueError, match=f"^{name} must be a number, got {re.escape(repr(value))}$"):
        TimestepSchedule(**{name: value})
