"""Training: the on-device loop (``loop``), the trainer (``trainer``, ``config``, ``runfolder``, ``sharding``,
``checkpoint``), evaluation (``evaluate``, ``dm_backend``), ``video``, ``report`` and the command line (``cli``).

This package is also callable: ``lnnmpc.train(config)`` is :func:`lnnmpc.train.trainer.train` (the package and
the function share the name ``lnnmpc.train``, so the package module forwards calls to the function).
"""

import sys
import types


class _CallablePackage(types.ModuleType):
    def __call__(self, *args, **kwargs):
        from lnnmpc.train.trainer import train

        return train(*args, **kwargs)


sys.modules[__name__].__class__ = _CallablePackage
