"""Packaging is declared in setup.cfg; this file adds one thing setup.cfg
cannot say: the shipped configs (configs/*.py) installed as the package
``slotformer_jax.configs``, so ``--config=configs/<name>.py`` finds them
after a non-editable ``pip install .``, from any folder
(``config.checks.shipped_config``)."""

import setuptools

setuptools.setup(
    packages=[*setuptools.find_packages(include=['slotformer_jax*']),
              'slotformer_jax.configs'],
    package_dir={'slotformer_jax.configs': 'configs'})
