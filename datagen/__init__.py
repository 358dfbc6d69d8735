"""The data lab: generating the offline datasets the model trains on.

Behaviour policies and their snapshots (`behaviour`: the snapshot kinds and their loaders), PPO training of
behaviour agents (`train_behaviour`, `train_commanded`, `refine_behaviour`, `ppo_state`), scripted gaits
(`gait`), planned braking (`plan`), start states (`start_states`), rollouts (`rollout`), collection into Minari
datasets (`collect`), the Breakout RAM agents (`breakout`) and the `gmt data` command (`cli`). It depends on
`gmt.model` (datasets, checkpoints, the engine), never the reverse.
"""
