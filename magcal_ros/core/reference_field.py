"""Reference field magnitude from the IGRF model (ppigrf) or from the data themselves."""
import datetime

import numpy as np

from magcal_ros.core.ellipsoid import fit_ellipsoid


def igrf_total(lat_deg, lon_deg, alt_km, date):
    """IGRF total intensity in nT at a place and date.

    Parameters
    ----------
    lat_deg, lon_deg : float
        Geodetic latitude and longitude, degrees.
    alt_km : float
        Height above the ellipsoid, km.
    date : str or datetime.date
        'YYYY-MM-DD' or a date.
    """
    import ppigrf
    if isinstance(date, str):
        try:
            date = datetime.datetime.strptime(date, '%Y-%m-%d')
        except ValueError:
            raise ValueError(f'--igrf date must be YYYY-MM-DD, got {date!r}') from None
    elif isinstance(date, datetime.date) and not isinstance(date, datetime.datetime):
        date = datetime.datetime(date.year, date.month, date.day)
    if not (-90 <= lat_deg <= 90 and -360 <= lon_deg <= 360):
        raise ValueError(f'latitude/longitude out of range: {lat_deg}, {lon_deg}')
    be, bn, bu = ppigrf.igrf(lon_deg, lat_deg, alt_km, date)
    return float(np.sqrt(np.ravel(be)[0] ** 2 + np.ravel(bn)[0] ** 2 + np.ravel(bu)[0] ** 2))


def auto_magnitude(raw):
    """Magnitude for data without any reference: mean radius of sensor 1's ellipsoid, nT.

    With no reference the absolute scale of the sensors is not observable; this keeps the
    corrected magnitude equal to the average raw magnitude, so only the shape is corrected.

    raw (N, 3) nT.
    """
    ell = fit_ellipsoid(raw, 1.0)
    radii = np.linalg.norm(np.asarray(raw, float) - ell.b, axis=1)
    return float(np.median(radii))
