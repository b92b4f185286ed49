"""Training: the on-device loop (``loop``) and the command-line trainer (``cli``)."""
