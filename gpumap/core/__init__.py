"""The map core: the min-max map (mapper facade, storage, integration, rules, files, merge).

Imports only the backends and the basics (gpumap.errors, spec, geometry, reference, pings, limits,
atomic, memory, lie); never a layer, driver, viewer or command (tests/test_architecture.py).
"""
