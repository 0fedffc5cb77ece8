"""The demonstrations: generation, the dataset on disk, and the one window builder."""
