"""The policy: the network of the paper, its per-tag normaliser, and the policy file."""
