"""The data lab: generating the offline datasets the model trains on.

Behaviour policies and their snapshots (`behaviour`: the snapshot kinds and their loaders), the one PPO trainer
(`ppo`, with `ppo_state` to save and resume a learner) and its three configurations (`train_behaviour`: speed
levels, `train_commanded`: a speed-commanded actor, `refine_behaviour`: a level fine-tuned), scripted gaits
(`gait`), planned braking (`plan`), start states (`start_states`), rollouts (`rollout`), collection into Minari
datasets (`collect`), the Breakout RAM agents (`breakout`) and the `gmt data` command (`cli`). It depends on
`gmt.model` (datasets, checkpoints, the engine), never the reverse.
"""
