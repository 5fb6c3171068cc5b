"""``lenslesscam batch``: reconstruct every item of a manifest as Ray tasks.

A manifest (CSV or TOML) lists items: a measurement (or a glob over a folder), its calibration
(PSF, mask, shutter, filters, dark), a method (``fista``, ``auto``, ``udn`` and any other
method of ``lenslesscam recon``) and per-item options. Each item becomes one Ray task that runs
the very command ``lenslesscam recon METHOD`` runs (its parser, its loader, its solver, its
atomic writer), so a batch result equals the command's result. UDN items run as jobs in a run
folder per item (checkpoints, resume after a lost worker).

Modules: :mod:`app.batch.manifest` (reading and checking manifests, item hashes),
:mod:`app.batch.task` (one item, in a worker or in this process), :mod:`app.batch.state`
(the batch folder: lock, state file, cancel, status), :mod:`app.batch.driver` (the Ray driver),
:mod:`app.batch.summary` (the summary tables). Ray is imported only by the driver, lazily.
"""
