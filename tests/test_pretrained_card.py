"""The steps a model card counts, on the three card shapes that exist: from scratch, a warm start recorded with its
chain's total, and one written before cards counted chains (the source's own steps only)."""

from depthnerf.pretrained.card import total_steps, warm_start_steps


def test_from_scratch_counts_its_own_steps():
    card = {"step": 2000}
    assert warm_start_steps(card) is None and total_steps(card, 2000) == 2000
    assert warm_start_steps({"step": 5, "init_from": None}) is None


def test_warm_start_with_its_chain_recorded():
    card = {"step": 3000, "init_from": {"step": 3000, "total_steps": 10000}, "total_steps": 13000}
    assert warm_start_steps(card) == 10000 and total_steps(card, 3000) == 13000


def test_card_written_before_chains_were_counted():
    card = {"step": 3000, "init_from": {"step": 2000}}
    assert warm_start_steps(card) == 2000 and total_steps(card, 3000) == 5000


def test_a_recorded_total_wins_over_the_sum():
    """``total_steps`` may count more than own + source's own steps (a longer chain); it is never recomputed."""
    card = {"step": 3000, "init_from": {"step": 3000}, "total_steps": 11000}
    assert total_steps(card, 3000) == 11000 and total_steps({"total_steps": None, "step": 7}, 7) == 7
