"""gaia_app: train and run the GAIA-1 and GAIA-2 generative world models for autonomous driving."""

__version__ = "0.1.0"

DRIVE_ENV = "gaia_app/Drive-v0"


def register_envs() -> None:
    """Register the closed-loop simulator with Gymnasium (docs/simulator.md): `gymnasium.make(DRIVE_ENV,
    weights="gaia1")` and `gymnasium.make_vec(DRIVE_ENV, num_envs=N)` (one batched forward for N episodes).
    Gymnasium 1.x has no plugin entry points, so this runs on `import gaia_app`; the entry points are strings, so
    nothing heavy (torch, the weights) loads before an env is made."""
    import gymnasium

    if DRIVE_ENV not in gymnasium.registry:
        gymnasium.register(DRIVE_ENV, entry_point="gaia_app.pipelines.simulator:make_env",
                           vector_entry_point="gaia_app.pipelines.vector_simulator:make_vector_env",
                           max_episode_steps=None, nondeterministic=False)


register_envs()
