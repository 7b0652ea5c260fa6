"""The token decoder: fitted for a policy whose encoder cannot decode (EfficientNet-Lite0), shown in eval videos and
``diagnose world-model``'s ``futures.png``; its file refused when it cannot serve."""

from __future__ import annotations

import pathlib
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from dust_rl.agents import PolicyConfig, load_policy
from dust_rl.agents.encoders.token_decoder import (
    TOKEN_DECODER_FILE,
    TokenDecoder,
    TokenDecoderConfig,
    load_token_decoder,
    save_token_decoder,
)
from dust_rl.cli import main
from dust_rl.data import DemoDataset
from dust_rl.data.video import read_mp4
from dust_rl.diagnose.world_model import WorldModelDiagnosis, diagnose
from dust_rl.errors import CheckpointError, ConfigError
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate
from dust_rl.evaluate.video import LABEL_HEIGHT, future_decoder
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.train.imitation import TrainConfig, train
from dust_rl.train.settings import LoggingSettings, OptimSettings, TrainRuntime
from dust_rl.train.token_decoder_fit import fit_token_decoder

pytestmark = pytest.mark.usefixtures("one_thread")

IMAGE = 32  # the demo dataset's frames
QUIET = RuntimeSettings(threads=1, progress=False)
TINY = {"horizon": 4, "d_model": 32, "n_heads": 2, "n_mmdit": 2, "n_dit": 0}


@pytest.fixture(scope="module")
def lite0(demo_dir, tmp_path_factory):
    """Tiny DUST and action-only policies on EfficientNet-Lite0 tokens (no decoder of their own), their dataset, a
    held-out copy, and a token decoder fitted beside the DUST policy."""
    root = tmp_path_factory.mktemp("token_decoder")
    data = shutil.copytree(demo_dir, root / "data")
    policies = {}
    for variant in ("dust", "action_only"):
        config = TrainConfig(dataset=data, out=root / variant, optim=OptimSettings(steps=4, batch_size=8),
                             logging=LoggingSettings(checkpoint_every=4, loggers=("csv",)),
                             runtime=TrainRuntime(threads=1, progress=False),
                             policy=PolicyConfig(**TINY, variant=variant, image_encoder="efficientnet-lite0-s8"))
        policies[variant] = train(config).policy
    policy = load_policy(policies["dust"])
    fit = fit_token_decoder(policy, DemoDataset(data), policies["dust"].parent / TOKEN_DECODER_FILE,
                            image_size=IMAGE, steps=150, batch_size=16, lr=3e-3, warmup=5, holdout_every=3,
                            loggers=("csv", "tensorboard"), progress=False)
    return policies, data, shutil.copytree(demo_dir, root / "heldout"), fit


def test_a_fitted_decoder_draws_unseen_frames_better_than_their_mean(lite0):
    policies, _, _, fit = lite0
    assert fit.heldout_mse < fit.mean_frame_mse, (fit.heldout_mse, fit.mean_frame_mse)
    decoder = load_token_decoder(fit.path)
    policy = load_policy(policies["dust"])
    assert future_decoder(policy) is None  # Lite0 cannot decode its own tokens
    tokens = torch.randn(3, policy.config.n_vision_tokens, policy.config.vision_dim)
    images = future_decoder(policy, decoder)(tokens)
    assert images.shape == (3, 3, IMAGE, IMAGE) and images.min() >= 0 and images.max() <= 1
    panel = Image.open(fit.path.with_suffix(".png"))
    assert panel.width == 2 * IMAGE and panel.height % (IMAGE + LABEL_HEIGHT) == 0
    assert list((fit.path.parent / "logs" / "token_decoder").rglob("events.out.tfevents.*"))  # the frames logged
    assert load_checkpoint_info(fit.path)["heldout_mse"] == fit.heldout_mse


def load_checkpoint_info(path: pathlib.Path) -> dict:
    return torch.load(path, weights_only=True)["info"]


def test_eval_videos_show_the_prediction_once_a_decoder_sits_beside_the_policy(lite0, tmp_path):
    policies, _, _, fit = lite0
    widths = {}
    bare = shutil.copy(policies["dust"], tmp_path / "policy.pt")  # no decoder beside this copy
    for name, path in (("bare", bare), ("decoded", policies["dust"])):
        report = evaluate(EvalConfig(policy=path, out=tmp_path / name, episodes=1, workers=1, max_steps=4,
                                     runtime=QUIET))
        frames = list(read_mp4(pathlib.Path(report["tasks"][0]["videos"][0]["path"])))
        widths[name] = (frames[0].shape[1], report["token_decoder"])
    # front and wrist, then the predicted and the real future of the front camera
    assert widths == {"bare": (2 * IMAGE, None), "decoded": (4 * IMAGE, str(fit.path))}


def test_diagnose_draws_predicted_futures_with_the_decoder(lite0, tmp_path):
    policies, _, heldout, fit = lite0
    report = diagnose(WorldModelDiagnosis(policy=policies["dust"], dataset=heldout, out=tmp_path, windows=16,
                                          tau_buckets=1, runtime=QUIET))
    assert report["futures"] == {"figure": str(tmp_path / "futures.png"), "token_decoder": str(fit.path)}
    figure = np.asarray(Image.open(tmp_path / "futures.png"))
    rows = figure.shape[0] // (IMAGE + LABEL_HEIGHT)
    assert figure.shape[1] == 4 * IMAGE and 1 < rows <= len(DemoDataset(heldout).lengths)  # one row per episode
    other = diagnose(WorldModelDiagnosis(policy=policies["action_only"], dataset=heldout, out=tmp_path / "ao",
                                         windows=16, tau_buckets=1, runtime=QUIET))
    assert other["futures"] is None and not (tmp_path / "ao" / "futures.png").exists()


def test_a_decoder_for_other_tokens_or_a_damaged_one_is_refused(lite0, tmp_path):
    policies, _, _, fit = lite0
    policy = load_policy(policies["dust"])
    other = TokenDecoder(TokenDecoderConfig(policy.backbone.image.reference(), 4, policy.config.vision_dim + 1, IMAGE))
    with pytest.raises(CheckpointError, match="fit-decoder"):
        future_decoder(policy, other)
    damaged = load_token_decoder(fit.path)
    with torch.no_grad():
        damaged.token_std[0] = float("nan")
    save_token_decoder(damaged, tmp_path / "nan.pt")
    with pytest.raises(CheckpointError, match="NaN"):
        load_token_decoder(tmp_path / "nan.pt")
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint")
    for path in (tmp_path / "garbage.pt", policies["dust"]):  # unreadable; a policy, not a decoder
        with pytest.raises(CheckpointError):
            evaluate(EvalConfig(policy=policies["dust"], decoder=path, out=tmp_path / "eval", episodes=1, workers=1,
                                max_steps=2, runtime=QUIET))


def test_fit_decoder_command(lite0, tmp_path, capsys):
    policies, data, _, _ = lite0
    policy = shutil.copy(policies["dust"], tmp_path / "policy.pt")
    args = ["encoder", "fit-decoder", "--policy", str(policy), "--dataset", str(data), "--image-size", str(IMAGE),
            "--runtime.no-progress"]
    main([*args, "--steps", "2", "--loggers", "csv"])
    assert f"{tmp_path / TOKEN_DECODER_FILE}: 2 steps" in capsys.readouterr().out
    assert load_checkpoint_info(tmp_path / TOKEN_DECODER_FILE)["command"].startswith("dust-rl encoder fit-decoder")
    with pytest.raises(SystemExit, match="predicts no future to decode"):
        main(["encoder", "fit-decoder", "--policy", str(policies["action_only"]), "--dataset", str(data),
              "--runtime.no-progress"])
    with pytest.raises(SystemExit, match="power of 2"):
        main([*args, "--image-size", "48"])
    with pytest.raises(SystemExit):
        main([*args, "--steps", "0"])
    with pytest.raises(ConfigError, match="no future to decode"):
        fit_token_decoder(load_policy(policies["action_only"]), DemoDataset(data), tmp_path / "x.pt", progress=False)
