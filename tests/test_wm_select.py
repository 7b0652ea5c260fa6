"""experiments/wm_select/wm_select.py: best of K joint samples by a scorer of the predicted future, and the study's
run (rollouts, the scorer's fit, the base and each K on the same held-out seeds)."""

from __future__ import annotations

import importlib.util
import pathlib

import pytest
import torch
from tensordict import NonTensorStack, TensorDict

from dust_rl.agents import AutoencoderConfig, ConvAutoencoder, load_policy, make_policy, save_policy
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate
from dust_rl.runtime.settings import RuntimeSettings

_SPEC = importlib.util.spec_from_file_location(
    "wm_select", pathlib.Path(__file__).parents[1] / "experiments" / "wm_select" / "wm_select.py")
wm_select = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(wm_select)

pytestmark = pytest.mark.usefixtures("one_thread")

EPISODE_STEPS = 10
CAMERAS = ["front", "wrist"]


def perturbed(policy):
    """``policy`` with every trainable weight moved off its initialisation (zero-initialised outputs ignore the
    inputs)."""
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in policy.trainable_parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))
    return policy


def test_best_of_k_executes_the_sample_whose_predicted_future_scores_best(tiny_encoder, minilm):
    policy = perturbed(make_policy("dust", image_encoder=tiny_encoder, text_encoder=minilm, cameras=CAMERAS,
                                   horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=1, action_dim=3, state_dim=5))
    scorer = wm_select.FutureScorer(policy.config.n_vision_tokens, policy.config.vision_dim, 8)
    with torch.no_grad():
        for p in scorer.parameters():
            p.normal_(generator=torch.Generator().manual_seed(1))
    g = torch.Generator().manual_seed(0)
    obs = TensorDict({"observation": {"image": {cam: torch.randint(0, 256, (2, 3, 32, 32), dtype=torch.uint8,
                                                                   generator=g) for cam in CAMERAS},
                                      "state": torch.randn(2, 5, generator=g)}}, batch_size=(2,))
    obs["language_instruction"] = NonTensorStack.from_list(["press the red button", "open the drawer"])
    # One candidate: the base policy's chunk, bit for bit.
    base = policy.plan(obs, torch.Generator().manual_seed(0))
    with wm_select.BestOfK(policy, scorer, 1):
        assert torch.equal(policy.plan(obs, torch.Generator().manual_seed(0))["action_chunk"], base["action_chunk"])
    # K candidates: the same draws as planning each observation K times, and the best-scoring one is kept.
    k = 3
    with wm_select.BestOfK(policy, scorer, k):
        chosen = policy.plan(obs, torch.Generator().manual_seed(1))
    every = policy.plan(obs[torch.arange(2).repeat_interleave(k)], torch.Generator().manual_seed(1))
    with torch.no_grad():
        scores = scorer(policy.standardised_future(every["future_tokens"])).view(2, k)
    best = every["action_chunk"].view(2, k, 6, 3)[torch.arange(2), scores.argmax(-1)]
    assert torch.equal(chosen["action_chunk"], best) and scores.std() > 0
    # Leaving the block restores the policy's own planning.
    assert "plan_features" not in vars(policy)


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory, minilm):
    """A tiny untrained policy for 32 px front + wrist cameras, its weights moved off their initialisation."""
    encoder = ConvAutoencoder(AutoencoderConfig(image_size=32, dim=16, width=8, max_width=16))
    policy = perturbed(make_policy("dust", image_encoder=encoder, text_encoder=minilm, cameras=CAMERAS, action_dim=7,
                                   state_dim=17, horizon=4, execute_steps=2, d_model=32, n_heads=2, n_mmdit=2,
                                   n_dit=0))
    policy.set_action_bounds(-torch.ones(7), torch.ones(7))  # DustFranka-v0's action box, as training sets it
    policy.info = {"env_id": "DustFranka-v0", "env_kwargs": {"image_size": 32}, "tasks": ["press_button"],
                   "image_size": [32, 32]}
    return save_policy(policy, tmp_path_factory.mktemp("policy") / "policy.pt")


def test_the_study_compares_the_base_and_best_of_k_on_the_same_seeds(policy_path, tmp_path):
    out = tmp_path / "wm"
    report = wm_select.main(["--policy", str(policy_path), "--out", str(out), "--candidates", "2", "--rollouts", "5",
                             "--scorer-hidden", "8", "--scorer-steps", "3", "--eval-episodes", "2", "--max-steps",
                             str(EPISODE_STEPS), "--device", "cpu", "--no-progress"])
    assert [row["task"] for row in report["rows"]] == ["base policy", "wm_select (K = 2)"]
    assert report["rollout_env_steps"] == 5 * EPISODE_STEPS and report["scorer"]["validation_rows"] > 0
    # The base row is the policy as dust-rl eval runs it, episode for episode.
    settings = dict(episodes=2, workers=1, videos=0, max_steps=EPISODE_STEPS,
                    runtime=RuntimeSettings(device="cpu", progress=False))
    evaluated = evaluate(EvalConfig(policy=policy_path, out=tmp_path / "eval", **settings))
    assert report["per_episode"]["base policy"] == evaluated["tasks"][0]["per_episode"]
    # The written scorer, read back, selects the same chunks.
    saved = torch.load(out / wm_select.SCORER_FILE, weights_only=True)
    policy = load_policy(policy_path)
    scorer = wm_select.FutureScorer(policy.config.n_vision_tokens, policy.config.vision_dim, saved["hidden"])
    scorer.load_state_dict(saved["state_dict"])
    with wm_select.BestOfK(policy, scorer.eval(), 2):
        again = evaluate(EvalConfig(policy=policy_path, out=tmp_path / "eval_k2", **settings), policy=policy)
    assert again["tasks"][0]["per_episode"] == report["per_episode"]["wm_select (K = 2)"]
    # The K row says which episodes it won and lost against the base, seed for seed.
    outcome = {e["seed"]: e["success"] for e in report["per_episode"]["base policy"]}
    selected, chosen = report["rows"][1]["vs_base"], again["tasks"][0]["per_episode"]
    assert "vs_base" not in report["rows"][0]
    assert selected["gained"] == sum(e["success"] and not outcome[e["seed"]] for e in chosen)
    assert selected["lost"] == sum(outcome[e["seed"]] and not e["success"] for e in chosen)
    assert "| wm_select (K = 2) | 2 |" in (out / "report.md").read_text()
