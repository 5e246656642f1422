"""File I/O, each format with its validation, never pickle: part models (``model_files``: model.yaml and its optional
``candidates:``, ``mesh``), displacement fields (``fields``, .vtu), scans (``ply``; ``scans``: a scan file to a field),
the ensemble store (``ensemble_store``, ``hdf5``), saved bases (``bases``), rosbag2 bags (``bags``), and JSON
(``json_values``: non-finite numbers become null; ``close_loop_report``: close_loop.json).

No re-exports here: importing one format does not load the libraries of the others (h5py, meshio, rosbags).

May import: ``hood_decomp.core`` and ``hood_decomp.errors``.
"""
