"""Layers that attach to a map (:meth:`gpumap.MinMaxMapper.attach`): they import the core, never the reverse."""
