"""The training application around the library: ``train.py``'s config schemas, resume and
checkpoints, signals, TensorBoard and console output, the block experiment, results.

This is the only part of ``dipole_torch`` that imports Hydra or TensorBoard; the library
(everything else under ``dipole_torch``) imports neither, nor the tasks or models.
"""
