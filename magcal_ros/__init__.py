"""magcal_ros: calibration and live correction of a four-fluxgate cross gradiometer.

Layers (see docs/design.md §6):

- :mod:`magcal_ros.core` -- numpy/scipy only: models, fits, diagnostics, simulator.
- :mod:`magcal_ros.io` -- CSV, rosbag2 and calibration-file readers/writers.
- :mod:`magcal_ros.serial` -- device protocol parsers and the pyserial transport.
- :mod:`magcal_ros.ros` -- the only modules that import rclpy (nodes, message conversions).

Importing this package, ``core``, ``io``, ``serial`` or ``cli`` never imports rclpy.
"""

__version__ = '0.1.0'
