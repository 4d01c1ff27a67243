"""Media bandwidth benchmarks against the Robot Web Tools paper (section IV): camera
(camera.py), TF (tf.py), point clouds (cloud.py) and maps (map.py); each has a
``measure_*`` function and a ``main()``. ``benchmarks/media_bandwidth.py`` runs them all
side by side and prints one table."""
