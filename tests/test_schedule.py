import pytest
import torch

from voxe_core.schedule import AUTHORS_FLOOR, PAPER_FLOOR, TimestepSchedule


@pytest.mark.parametrize(
    "iteration, k",
    [
        (0, 0.98),
        (3999, 0.98),
        (4000, 0.98 * 0.75),  # first decay at i_start
        (4599, 0.98 * 0.75),
        (4600, 0.98 * 0.75**2),
        (5200, 0.98 * 0.75**3),
        (5799, 0.98 * 0.75**3),  # 0.413 > 0.35
        (5800, 0.35),  # 0.98 * 0.75**4 = 0.310 -> floor
        (20000, 0.35),
    ],
)
def test_paper_schedule(iteration, k):
    assert TimestepSchedule().max_fraction(iteration) == pytest.approx(k, abs=1e-12)


def test_authors_floor():
    s = TimestepSchedule.authors()
    assert AUTHORS_FLOOR == 0.22 and s.floor == 0.22 and PAPER_FLOOR == 0.35
    assert s.max_fraction(5800) == pytest.approx(0.98 * 0.75**4)  # 0.310, above 0.22
    assert s.max_fraction(6400) == pytest.approx(0.98 * 0.75**5)  # 0.233
    assert s.max_fraction(7000) == pytest.approx(0.22)  # 0.174 -> floor
    assert s.max_fraction(20000) == pytest.approx(0.22)
    assert TimestepSchedule(floor=AUTHORS_FLOOR).max_fraction(20000) == pytest.approx(0.22)


def test_schedule_is_monotone_non_increasing():
    s = TimestepSchedule()
    values = [s.max_fraction(i) for i in range(0, 9000, 50)]
    assert all(b <= a for a, b in zip(values, values[1:]))


@pytest.mark.parametrize("iteration, lo, hi", [(0, 20, 980), (4000, 20, 735), (4600, 20, 551), (20000, 20, 350)])
def test_samples_within_range(iteration, lo, hi):
    s = TimestepSchedule()
    assert s.bounds(iteration) == (lo, hi)
    t = s.sample(iteration, 20000, generator=torch.Generator().manual_seed(0))
    assert t.dtype == torch.long and t.shape == (20000,)
    assert int(t.min()) == lo and int(t.max()) == hi  # both ends reachable, nothing outside
    # roughly uniform: mean near the middle
    assert float(t.float().mean()) == pytest.approx((lo + hi) / 2, rel=0.02)


def test_sample_reproducible_and_scaled_by_T():
    s = TimestepSchedule()
    a = s.sample(0, 8, generator=torch.Generator().manual_seed(1))
    b = s.sample(0, 8, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a, b)
    t = s.sample(0, 5000, num_train_timesteps=100, generator=torch.Generator().manual_seed(2))
    assert int(t.min()) >= 2 and int(t.max()) <= 98


def test_invalid_schedules_rejected():
    with pytest.raises(ValueError):
        TimestepSchedule(floor=0.01)
    with pytest.raises(ValueError):
        TimestepSchedule(every=0)
    with pytest.raises(ValueError):
        TimestepSchedule().max_fraction(-1)
