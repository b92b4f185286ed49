"""lnnmpc: TD-MPC2 with liquid recurrent history encoders, on MJX."""
