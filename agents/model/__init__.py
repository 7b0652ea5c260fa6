"""The trunk: DUST's dual-stream velocity network and its baselines, with the flow-matching loss and the samplers.

It works on encoded, normalised inputs (condition tokens, state, action chunk, future tokens) and knows nothing of
cameras, encoders or read-outs, so it imports only the agents' config (the policy feeds it, :mod:`..policy`).
"""
