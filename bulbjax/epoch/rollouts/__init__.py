"""The environment's side of an epoch: PPO's rollouts and what reaches the learners of them.

`policy` (`Policy`: PPO's rollouts and updates, `rl_phase`), `observations` (what PPO observes,
one class per `--rl-input` form) and `streams` (`Streams`: the rollouts' frames and windows into
replay and the window buffers, the held-out streams the probes read). Entered from
`bulbjax.epoch` by the epoch (`loop`) and the offline fit's programs (`offline`) only; it imports
the epoch's lower parts (`devices`, `seeds`, `state`), never the epoch that drives it, the
learners' updates or the probes (tests/test_imports.py, `FOLDERS`).
"""
