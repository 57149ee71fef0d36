"""gaia_app: train and run the GAIA-1 and GAIA-2 generative world models for autonomous driving."""

__version__ = "0.1.0"
