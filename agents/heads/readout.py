"""The read-out of the privileged object state: one optional head of the policy, whichever network it is.

Every dataset row also stores the simulator's object positions (``env_state``), which the policy never reads
when acting but may learn from: a read-out estimates that state (normalised) from what the trunk is conditioned
on, its squared error joins the training loss (``lambda_aux``) and, with ``aux_state_input``, the estimate joins
the robot state the trunk reads. It reads either the keypoints' coordinates (:mod:`.state_readout`) or every
camera's frozen tokens (:mod:`.token_readout`). This head is where that choice lives: the policy holds one (None
without a read-out), hands it both inputs and asks it what it reads.

Frames without actions alone can fit a read-out (``--readout.aux-frames``, ``--readout.warmup-steps``) when they
give all it reads: the frozen tokens, or pixel keypoints. Keypoints on the frozen tokens also train through the
action loss, so they cannot.

A plain object, not a module: its network stays registered on the policy as ``state_readout``, and the keypoints
in the policy's condition projector, the names policy files, training checkpoints and cached read-out fits store
their weights by (a submodule would rename them).
"""

from __future__ import annotations

from torch import Tensor, nn

from ..config import DustConfig
from .state_readout import StateReadout
from .token_readout import TokenReadout

NO_FRAME_READOUT = ("this needs a state read-out on the image tokens (--model.lambda-aux with --model.readout "
                    "tokens) or on pixel keypoints (--model.keypoint-source pixels)")


class ObjectStateReadout:
    """A read-out network, what it reads, and what a fit on frames trains.

    Args:
        network: a :class:`.token_readout.TokenReadout` or a :class:`.state_readout.StateReadout` (on keypoints).
        keypoints: the keypoint heads of the condition projector, which a keypoint read-out reads.
        pixel_keypoints: whether those heads read the raw frames (a keypoint read-out frames can then fit).
    """

    def __init__(self, network: TokenReadout | StateReadout, keypoints: nn.ModuleList, pixel_keypoints: bool) -> None:
        self.network, self.keypoints = network, keypoints
        self.reads_tokens = isinstance(network, TokenReadout)
        self.reads_frames = self.reads_tokens or pixel_keypoints
        """Whether frames without actions can fit it (module doc)."""

    def estimate(self, image: Tensor | None, keypoints: Tensor | None, text: Tensor, text_mask: Tensor,
                 state: Tensor) -> Tensor:
        """The estimate [B, S] of the normalised object state from the standardised image tokens [B, C, N, Dv] on the
        token grid or the keypoint features [B, C*K, 2 + D], whichever it reads (the other may be None), the
        instruction's tokens and mask, and the normalised robot state [B, Ds] (a token read-out with
        ``readout_proprio`` reads it)."""
        if self.reads_tokens:
            return self.network(image, text, text_mask, state)
        return self.network(keypoints, text, text_mask)

    def frame_modules(self) -> nn.ModuleDict:
        """The network (and the pixel keypoint heads it reads): what ``--readout.warmup-steps`` fits and then freezes,
        by the names cached fits store them under.

        Raises:
            ValueError: frames alone cannot fit this read-out.
        """
        if not self.reads_frames:
            raise ValueError(NO_FRAME_READOUT)
        if self.reads_tokens:
            return nn.ModuleDict({"state_readout": self.network})
        return nn.ModuleDict({"keypoints": self.keypoints, "state_readout": self.network})


def squared_error(estimate: Tensor, target: Tensor) -> Tensor:
    """The read-out's loss: mean squared error of the normalised object state."""
    return (estimate - target).square().mean()


def object_state_readout(config: DustConfig, cameras: int, image_dim: int, text_dim: int,
                         keypoints: nn.ModuleList) -> ObjectStateReadout | None:
    """The read-out ``config`` asks for (None without ``aux_state_dim``), reading ``cameras`` cameras' tokens of size
    ``image_dim`` or their ``keypoints``, and instruction tokens of size ``text_dim``."""
    if not config.aux_state_dim:
        return None
    if config.readout == "tokens":
        network = TokenReadout(cameras, config.token_grid, image_dim, text_dim, config.aux_state_dim,
                               config.readout_heads, config.state_dim if config.readout_proprio else 0,
                               config.readout_text == "attention")
    else:
        network = StateReadout(cameras * config.keypoints, text_dim, config.aux_state_dim)
    return ObjectStateReadout(network, keypoints, config.keypoint_source == "pixels")
