"""A user's CartPole policy for `gmt data collect --policy tests.datagen.cartpole_policy:careful` (tests and
docs/your-own-data.md's example)."""


def careful(obs, level, rng):
    """A balancing controller that acts at random with probability `level` (e.g. "0.05" careful, "0.6" sloppy)."""
    x, v, th, om = obs
    action = int(th + 0.3 * om + 0.02 * x + 0.05 * v > 0)
    return action if rng.random() >= float(level) else int(rng.integers(2))
