"""Plant definitions, their configuration and the catalogue under ``conf/plants``."""
