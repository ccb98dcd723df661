"""Pure numpy kernels of the BTF pipeline (and a few compiled loops, :mod:`tasks.csr_kernel`).

Everything here takes and returns numpy arrays (and small frozen dataclasses), is deterministic
given its seed, and never imports dask, zarr, xarray or OpenEXR, nor touches files. The
orchestration that maps these kernels over chunks lives in :mod:`pipeline`.
"""
