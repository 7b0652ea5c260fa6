"""The frozen backbone: image encoders (a conv autoencoder, EfficientNet-Lite, ``transformers`` ViTs) and the text
encoder, built from a reference a policy file stores and never trained with the policy.

They turn pixels and instructions into tokens and import nothing else of the agents but the config's size caps, so
the trunk, the heads and the policy can all read their outputs.
"""
