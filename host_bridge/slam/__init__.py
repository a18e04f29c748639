"""Host-side 2D SLAM: the robot sends raw scans and odometry, the PC builds the map.

``engine`` matches scans and keeps the pose graph (small_gicp, GTSAM), ``grid`` the occupancy,
``feeder`` runs it per robot inside the host and logs what it finds, ``files`` writes
``--save-map``. Imported only when SLAM is on: GTSAM is the ``[slam]`` extra.
"""
