"""Optional trainable heads on the trunk's inputs: keypoints on the frozen feature map or the raw pixels (condition
tokens of their own) and the read-outs of the privileged object state (an auxiliary loss, and an estimate the trunk
may read).

They read the encoders' outputs (frozen tokens, instruction tokens) and never the trunk or the policy that holds
them.
"""
