"""Reusable dask graph builders: block geometry, reductions, applying prescriptions, surfaces.

A builder works out chunks, halos and seeds and maps a kernel of :mod:`tasks` over them, and
returns the graph for a stage to compute on its :class:`pipeline.session.Session`. Two
functions run their graphs themselves, because they are sequences of them: the write both
tile-set stages end with (:func:`pipeline.graphs.prescriptions.write_tileset`), and tiled
enlargement, level after level (:func:`pipeline.graphs.enlarge.synthesize`).
"""
