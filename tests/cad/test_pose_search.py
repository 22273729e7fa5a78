"""The hypothesis search of the registration: poses scored in batches as one at a time."""

import numpy as np

from partinspect.simulate.measured import measure_features


def test_poses_scored_together_score_as_one_at_a_time(scene):
    # The search scores its hypotheses in batches; each pose's matches and
    # cost are those of matching it alone, whichever batch it falls in.
    from partinspect.cad import pose_search as reg_mod

    _, inv, T, ids = scene
    m = measure_features(inv, T, ids, np.random.default_rng(5), n_points=0)
    meas, cad = reg_mod.measured_arrays(m.circles, m.lines), reg_mod.cad_arrays(inv)
    hyps = reg_mod._circle_hypotheses(meas, cad) + reg_mod._line_hypotheses(meas, cad)
    assert len(hyps) > 20
    one = []
    for R, t in hyps:
        circ, lin, cost = reg_mod.match(meas, cad, R, t)
        one.append((len(circ) + len(lin), cost))
    batched = reg_mod._scores(meas, cad, hyps, batch=7)
    assert [n for n, _ in batched] == [n for n, _ in one]
    assert np.allclose([c for _, c in batched], [c for _, c in one], rtol=1e-12, atol=0)
    # The true pose is among the best scored, with every feature matched.
    assert max(n for n, _ in batched) == len(m.circles) + len(m.lines)
