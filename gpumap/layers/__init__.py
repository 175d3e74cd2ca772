"""Layers that attach to a map (:meth:`gpumap.MinMaxMapper.attach`).

They import the core, never the reverse."""
