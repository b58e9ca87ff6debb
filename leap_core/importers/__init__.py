"""Importers: write a recording in another format as the KITTI layout the rest of LeAP reads
(``velodyne/``, ``image_2/``, ``calib.txt``, ``poses.txt`` when known, ``times.txt``)."""
