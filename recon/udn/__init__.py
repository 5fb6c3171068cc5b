"""Untrained deep network (UDN, deep image prior) reconstruction: network, runner, jobs.

- :mod:`recon.udn.network`: the encoder-decoder G(z; W) with skips, 2D / frames / 3D.
- :mod:`recon.udn.runner`: :class:`UDNRunner`, the stepwise solver (Adam, held-out early
  stopping, divergence recovery, EMA), with an exact state for resuming.
- :mod:`recon.udn.memory`: the memory estimate and the refusal when a run will not fit.
- :mod:`recon.udn.spec`: TOML job specs and their validation.
- :mod:`recon.udn.jobs`: run folders: checkpoints, previews, loss history, results, run
  records; run, resume, status, cancel.
- :mod:`recon.udn.rundir`: the run folder's lock, verified checkpoints with a fallback, the
  clean-up of interrupted writes, a full disk named.
- :mod:`recon.udn.state`: :class:`~recon.udn.state.JobState` and
  :class:`~recon.udn.state.FinishReason`, the str-Enums of job states.

Torch is imported by these modules; import them only where torch is wanted.
"""

from recon.udn.network import Generator, NetworkConfig
from recon.udn.runner import UDNConfig, UDNResult, UDNRunner, UDNStep

__all__ = [
    "Generator",
    "NetworkConfig",
    "UDNConfig",
    "UDNResult",
    "UDNRunner",
    "UDNStep",
]
