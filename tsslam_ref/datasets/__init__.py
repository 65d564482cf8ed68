"""Dataset readers behind :mod:`tsslam_ref.data` (the public entry point; import from there).

Side layer: imports layer 0 (``geometry``) only.  One concept per file:

* ``intrinsics``  -- the pinhole camera, its exact crop/resize updates, calibration files;
* ``tum_format``  -- TUM text lists and trajectories, timestamp association, pose interpolation;
* ``images``      -- reading colour and 16-bit depth images, crop and resize;
* ``sequence``    -- ``Frame`` and the lazy ``RGBDSequence``;
* ``layouts``     -- the five folder layouts (TUM, ScanNet, NeuralRGBD, Replica, generic folder).

Formats and conventions are documented in docs/data.md; taught in notebooks/00_data_and_cameras.ipynb.
"""
