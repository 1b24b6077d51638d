"""optimize.prior: knowledge: the knowledge base decides, within the video's ranges, what the
video leaves weakly constrained; a synthetic flow model stands in for the simulation."""

import dataclasses

import pytest
import torch

from clflow.pipeline.fit import Optimization
from clflow.pipeline.fit.prior import Prior, decide, knowledge_priors, refitted_move
from clflow.pipeline.material import resolve_material
from clflow.query.knowledge import load_knowledge_base
from tests.pipeline.test_levenberg_marquardt import Z_TRUE, evaluation_of
from tests.pipeline.test_material import query_config

pytestmark = pytest.mark.usefixtures("points_one_by_one")


def test_the_prior_is_the_query_s_match_else_every_entry_of_the_type(quick_demo, tmp_path):
    kb = load_knowledge_base()
    cfg = query_config(
        quick_demo, tmp_path, {"type": "query", "query": {"prompt": "a ball of play-doh"}}, ("youngs_modulus",)
    )
    playdoh = kb.entry("play-doh").parameters["youngs_modulus"]
    prior = knowledge_priors(resolve_material(cfg))["youngs_modulus"]
    assert (prior.entry, prior.value, prior.low, prior.high) == ("play-doh", playdoh.value, playdoh.low, playdoh.high)
    assert prior.how == "the material query's match"
    (tmp_path / "b").mkdir()
    explicit = query_config(quick_demo, tmp_path / "b", {"type": "plasticine"}, ("poissons_ratio", "yield_stress"))
    priors = knowledge_priors(explicit)
    assert set(priors) == {"poissons_ratio", "yield_stress"}
    for name, prior in priors.items():
        entries = [e.parameters[name] for e in kb.entries if e.material == "plasticine"]
        assert (prior.low, prior.high) == (min(v.low for v in entries), max(v.high for v in entries))
        values = sorted(v.value for v in entries)
        assert prior.value == values[(len(values) - 1) // 2]
        assert prior.how == "the median of the plasticine entries, the union of their ranges"


def test_the_refit_cancels_what_the_moved_variables_change_to_first_order():
    g = torch.Generator().manual_seed(0)
    J = torch.randn(200, 3, generator=g, dtype=torch.float64)
    move = refitted_move(J, ("a", "b", "c"), {"b": 0.5})
    step = torch.tensor([move["a"], move["b"], move["c"]], dtype=torch.float64)
    assert move["b"] == 0.5
    # the residuals' change is orthogonal to the refitted columns: the least-squares refit
    assert torch.allclose(J[:, [0, 2]].T @ (J @ step), torch.zeros(2, dtype=torch.float64), atol=1e-10)
    assert refitted_move(J, ("a", "b", "c"), {}) == {"a": 0.0, "b": 0.0, "c": 0.0}


NU_FIT = -0.3  # the fit's Poisson's ratio: below every elastic entry's range (0 - 0.49)


@pytest.fixture
def synthetic(demo_config, monkeypatch):
    """The demo's elastic optimiser over E and nu with flows observed + noise + a shift that
    E moves, nu (``nu_weight``) barely or not at all, and E + ``coupling`` nu (in z) together;
    its fit at E = Z_TRUE, nu = NU_FIT."""

    def make(nu_weight: float, coupling: float = 0.0):
        cfg = demo_config()
        optimize = dataclasses.replace(cfg.optimize, parameters=("youngs_modulus", "poissons_ratio"), prior="knowledge")
        opt = Optimization(dataclasses.replace(cfg, optimize=optimize))
        g = torch.Generator().manual_seed(3)
        shape = opt.problem.views[0].observed.shape
        field_e, field_nu = (torch.randn(shape, generator=g, dtype=torch.float64) for _ in range(2))
        noise = 0.01 * torch.randn(shape, generator=g, dtype=torch.float64)
        nu_fit = float(opt.problem.params["poissons_ratio"].encode(NU_FIT))

        def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
            e, nu = z["youngs_modulus"] - Z_TRUE, z["poissons_ratio"] - nu_fit
            shift = (e + coupling * nu) * field_e + nu_weight * nu * field_nu
            flows = [opt.problem.views[0].observed[t] + noise[t] + shift[t] for t in range(frames)]
            return evaluation_of(opt, flows, frames, grid)

        monkeypatch.setattr(opt.objective, "evaluate", evaluate)
        z = {"youngs_modulus": Z_TRUE, "poissons_ratio": nu_fit}
        return opt, z, opt.diagnostics.identifiability(z, 1)

    return make


def weak_nu(opt, z, report, low=None, high=None, unresolved=False) -> dict:
    """``report`` saying that nu is weakly constrained (and ``unresolved``), its range
    ``low``..``high`` (None: open), E's the fit's alone, the loss tolerance 1 %: what a real
    grid check gives."""
    fit = opt.problem.values(z)
    ranges = {
        "youngs_modulus": {"low": fit["youngs_modulus"], "high": fit["youngs_modulus"]},
        "poissons_ratio": {"low": low, "high": high},
    }
    return {
        **report,
        "weakly_constrained": ["poissons_ratio"],
        "unresolved": ["poissons_ratio"] if unresolved else [],
        "loss_tolerance": 0.01,
        "ranges": ranges,
    }


def test_an_implausible_value_the_video_cannot_see_moves_into_the_prior_and_the_others_refit(synthetic):
    """nu changes nothing on its own but trades with E: the prior takes nu from the fit's
    -0.3 to the nearest plausible elastic value (0, the lowest of the knowledge base's
    elastic ranges), E follows to keep the flow."""
    opt, z, report = synthetic(nu_weight=0.0, coupling=0.1)
    assert "poissons_ratio" in report["weakly_constrained"]
    priors = knowledge_priors(opt.problem.cfg)
    assert (priors["poissons_ratio"].low, priors["poissons_ratio"].high) == (0.0, 0.49)
    decision = decide(opt.objective, z, 1, weak_nu(opt, z, report), priors)
    entry = decision.record["parameters"]["poissons_ratio"]
    assert entry["video_fit"] == pytest.approx(NU_FIT) and entry["prior_range"] == [0.0, 0.49]
    assert entry["decided_by"] == "prior" and decision.record["move"]["fraction"] == 1.0
    assert entry["value"] == pytest.approx(0.0, abs=1e-9)
    # E refitted: E + 0.1 nu (in z) held, so the flow is the fit's
    moved_nu = decision.z["poissons_ratio"] - z["poissons_ratio"]
    assert moved_nu > 0.5
    assert decision.z["youngs_modulus"] - z["youngs_modulus"] == pytest.approx(-0.1 * moved_nu, abs=1e-6)
    assert decision.record["parameters"]["youngs_modulus"]["decided_by"] == "video"
    assert decision.record["move"]["tried"] == [{"fraction": 1.0, "loss_ratio": pytest.approx(1.0, abs=1e-6)}]
    assert decision.result is not None and decision.result.loss == pytest.approx(
        opt.objective.evaluate(z, opt.problem.frames).loss, rel=1e-6
    )


def test_a_plausible_value_stays_and_an_interval_beyond_the_range_stops_at_its_end(synthetic):
    opt, z, report = synthetic(nu_weight=0.0, coupling=0.1)
    priors = knowledge_priors(opt.problem.cfg)
    wide = {**priors, "poissons_ratio": dataclasses.replace(priors["poissons_ratio"], low=-0.5)}
    decision = decide(opt.objective, z, 1, weak_nu(opt, z, report), wide)
    assert decision.z == z and decision.record["parameters"]["poissons_ratio"]["decided_by"] == "video"
    decision = decide(opt.objective, z, 1, weak_nu(opt, z, report, low=-0.5, high=-0.1), priors)
    entry = decision.record["parameters"]["poissons_ratio"]
    assert entry["decided_by"] == "range_end" and entry["value"] == pytest.approx(-0.1, abs=1e-9)


def test_an_unresolved_parameter_takes_the_prior_s_value_within_its_range(synthetic):
    """A flat loss: any value is the video's, so the prior's (the median of the elastic
    entries' nu) decides, cut to the range where that lies beyond."""
    opt, z, report = synthetic(nu_weight=0.0, coupling=0.1)
    priors = knowledge_priors(opt.problem.cfg)
    kb = load_knowledge_base()
    values = sorted(e.parameters["poissons_ratio"].value for e in kb.entries if e.material == "elastic")
    assert priors["poissons_ratio"].value == values[(len(values) - 1) // 2] == 0.3
    decision = decide(opt.objective, z, 1, weak_nu(opt, z, report, unresolved=True), priors)
    entry = decision.record["parameters"]["poissons_ratio"]
    assert entry["decided_by"] == "prior" and entry["value"] == pytest.approx(0.3, abs=1e-9)
    decision = decide(opt.objective, z, 1, weak_nu(opt, z, report, high=0.2, unresolved=True), priors)
    entry = decision.record["parameters"]["poissons_ratio"]
    assert entry["decided_by"] == "prior" and entry["value"] == pytest.approx(0.2, abs=1e-9)


def test_the_prior_moves_nothing_the_video_determines(synthetic):
    """nu determined by the flow: not weak, so the prior leaves the fit as it is."""
    opt, z, report = synthetic(nu_weight=1.0)
    assert report["weakly_constrained"] == [] and report["unresolved"] == []
    decision = decide(opt.objective, z, 1, report, knowledge_priors(opt.problem.cfg))
    assert decision.z == z and decision.result is None and decision.record["move"]["tried"] == []
    assert {e["decided_by"] for e in decision.record["parameters"].values()} == {"video"}


def test_a_move_that_leaves_the_loss_tolerance_is_not_kept(synthetic):
    """A report that calls a determined nu weak: every fraction of the move raises the loss
    beyond the tolerance, so the fit stays and the video decided."""
    opt, z, report = synthetic(nu_weight=1.0)
    decision = decide(opt.objective, z, 1, weak_nu(opt, z, report), knowledge_priors(opt.problem.cfg))
    assert decision.z == z and decision.result is None
    assert decision.record["move"]["fraction"] == 0.0 and len(decision.record["move"]["tried"]) == 3
    assert all(t["loss_ratio"] > decision.record["move"]["loss_limit_ratio"] for t in decision.record["move"]["tried"])
    assert decision.record["parameters"]["poissons_ratio"]["decided_by"] == "video"


def test_the_results_say_who_decided_each_parameter_and_a_run_confirms_each_move(demo_config, monkeypatch):
    """The demo's fit (E within 10 % of its truth, test_optimize) with a report that calls its
    E weak and unbounded, and a prior of 4-6 MPa (20-30x the demo's truth): every move tried
    raises the real runs' loss beyond the tolerance, so params.json keeps the video's E and
    metrics.json says so."""
    import json

    from clflow.pipeline.fit import prior
    from clflow.pipeline.runs import write_results

    cfg = demo_config()
    opt = Optimization(dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, prior="knowledge")))
    state = opt.run()
    measured = opt.diagnostics.identifiability

    def e_called_weak(z, substeps, search=None):
        report = measured(z, substeps, search)
        report["ranges"]["youngs_modulus"].update(low=None, high=None)
        return {**report, "weakly_constrained": ["youngs_modulus"]}

    stiff = {"youngs_modulus": Prior(5e6, 4e6, 6e6, "rubber", "a test's")}
    monkeypatch.setattr(opt.diagnostics, "identifiability", e_called_weak)
    monkeypatch.setattr(prior, "knowledge_priors", lambda cfg: stiff)
    metrics = write_results(opt, state)
    entry = metrics["prior"]["parameters"]["youngs_modulus"]
    assert (entry["entry"], entry["prior"], entry["prior_range"]) == ("rubber", 5e6, [4e6, 6e6])
    tried = metrics["prior"]["move"]["tried"]
    assert len(tried) == 3 and all(t["loss_ratio"] > metrics["prior"]["move"]["loss_limit_ratio"] for t in tried)
    assert entry["decided_by"] == "video" and entry["value"] == entry["video_fit"]
    params = json.loads((cfg.output / "params.json").read_text())
    assert params["optimized"]["youngs_modulus"] == entry["value"] == opt.problem.values(state.z)["youngs_modulus"]
