"""The shipped profiles and node graphs (YAML), installed as package data: see :func:`gsfix_online.core.config.configs_dir`."""
