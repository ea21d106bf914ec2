"""Unit constants and conversions shared by every layer (pure numpy, no rclpy).

The library works in nanotesla (nT), seconds and degrees Celsius; ROS messages carry SI
units (tesla, tesla per metre) per REP 103. The conversion to message units happens in
:mod:`magcal_ros.ros.conversions`, which uses these helpers.
"""

import numpy as np

#: Nanotesla per tesla.
NT_PER_T = 1e9


def nt_to_t(value_nt):
    """Convert nanotesla to tesla (also nT/m to T/m).

    Parameters
    ----------
    value_nt : array_like
        Field (or gradient) of any shape, in nT (or nT/m).

    Returns
    -------
    numpy.ndarray or float
        Same shape, float64, in T (or T/m). A scalar input gives a numpy float.
    """
    return np.asarray(value_nt, dtype=np.float64) / NT_PER_T


def t_to_nt(value_t):
    """Convert tesla to nanotesla (also T/m to nT/m).

    Parameters
    ----------
    value_t : array_like
        Field (or gradient) of any shape, in T (or T/m).

    Returns
    -------
    numpy.ndarray or float
        Same shape, float64, in nT (or nT/m). A scalar input gives a numpy float.
    """
    return np.asarray(value_t, dtype=np.float64) * NT_PER_T
