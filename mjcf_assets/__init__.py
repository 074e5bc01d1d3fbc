"""The MJCF models of the file-based domains (CartPole, InvertedPendulum, HalfCheetah, Ant, the
Rearrange reacher). This top-level folder of the checkout ships inside the wheel as the package
`bulbjax.mjcf_assets` (setup.py's `package_dir` mapping, pyproject.toml's package-data); the envs
find it through `bulbjax.envs.models.asset_dir`."""
