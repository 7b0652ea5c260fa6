"""An asymmetric actor-critic for SB3's SAC: the critic also reads the env's true object state, the actor does not.

The steering agent acts from what the frozen policy sees (pooled image tokens, the robot state, a read-out's
estimate), but its critic only serves training, so it may read privileged information: with where the objects
truly are (``observation.environment_state``, the view's ``object_state``: :mod:`dust_rl.rl.frozen_policy_env`)
it can tell states apart that the pooled features blur, as DSRL's critics read the low-dimensional state. The actor
never reads that entry, so the trained agent acts, in training and in closed loop, without it: ``predict`` takes an
observation without ``object_state`` (the closed-loop actor's, :attr:`AgentView.actor_view`).

:class:`AsymmetricSACPolicy` is SB3's ``MultiInputPolicy`` whose actor's features extractor is built on the
observation space without that entry (SAC's critic and target critic keep their own extractors, on all entries);
torchrl's front-end does the same with the critic's in_keys (:mod:`dust_rl.rl.torchrl_sac`).
"""

from __future__ import annotations

from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.sac.policies import Actor, MultiInputPolicy

from dust_rl.rl.frozen_policy_env import OBJECT_STATE


def actor_space(space: spaces.Dict) -> spaces.Dict:
    """``space`` without the critic's privileged entry."""
    return spaces.Dict({name: entry for name, entry in space.spaces.items() if name != OBJECT_STATE})


class AsymmetricSACPolicy(MultiInputPolicy):
    """SAC's ``MultiInputPolicy`` whose actor does not read ``object_state`` (module doc).

    Raises:
        ValueError: ``share_features_extractor`` (the critic would then read the actor's features only).
    """

    def __init__(self, *args, **kwargs) -> None:
        if kwargs.get("share_features_extractor"):
            raise ValueError("an asymmetric critic needs features extractors of its own (share_features_extractor)")
        super().__init__(*args, **kwargs)

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> Actor:
        extractor = self.features_extractor_class(actor_space(self.observation_space), **self.features_extractor_kwargs)
        return super().make_actor(extractor)
