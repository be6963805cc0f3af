"""Resection of a total-station setup from three measured angles (Ghilani 2010, Ex. 15.5).

What a surveyor learns: how ``minegeo.survey.resection_2d`` adjusts an unknown station U from
clockwise angles to four fixed control points by least squares, and how to read the result —
adjusted coordinates, their standard deviations, sigma0 with one degree of freedom, and the 95 %
error ellipse (with r = 1 the F-based 95 % factor is ~20 x the standard ellipse; semi-axes and azimuth of the major axis, clockwise from grid north). The book's
answer is U = (999.999, 1000.025) ft. Usage: ``python examples/adjust_resection.py``.
"""

import math

from minegeo.survey import format_dms, resection_2d

GON = math.pi / 200.0  # the published angles are in gon (as in the Krumm/Gama example file)
control = {"P": (1303.599, 1458.615), "Q": (1636.436, 1310.468),
           "R": (1503.395, 888.362), "S": (1506.262, 785.061)}
angles = [("P", "Q", 33.8805555555556 * GON), ("Q", "R", 42.7873456790123 * GON),
          ("R", "S", 11.6657407407407 * GON)]  # (backsight, foresight, clockwise angle at U)
sigmas = [0.00154320987654321 * GON, 0.00185185185185185 * GON, 0.00185185185185185 * GON]

st = resection_2d(control, angles=angles, sigma_angle_rad=sigmas, station="U", approx=(1000.0, 1000.0))
print(f"status {st.status}; dof {st.dof}; sigma0 {st.sigma0:.4f}")
print(f"U  E = {st.e_m:.4f}  N = {st.n_m:.4f}")
print(f"   sE = {st.se_m:.4f}  sN = {st.sn_m:.4f}")
e0, e = st.ellipse_standard, st.ellipse_95
print(f"standard ellipse: a = {e0.semi_major_m:.4f}, b = {e0.semi_minor_m:.4f} (1 sigma)")
print(f"95% ellipse: a = {e.semi_major_m:.4f}, b = {e.semi_minor_m:.4f}, "
      f"azimuth of a = {format_dms(e.azimuth_rad, width_deg=3)} (k = {e.k:.3f}, {e.basis})")
for o in st.network.observations:  # residual, redundancy number r_i and Baarda's w-test
    ob = o.obs
    print(f"  angle {ob.backsight}-{ob.station}-{ob.target}: v = {math.degrees(o.residual) * 3600:+.2f}\" "
          f"r = {o.redundancy:.3f} w = {o.w:+.2f}")
