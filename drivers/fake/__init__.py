"""Mock mode: a simulated station (deformable object, two Pandas, grippers, RGB-D camera).

World frame (fixed): z up, the table top is the plane z = 0, origin centred between the arm
bases; left arm base at (0, +0.45, 0), right at (0, -0.45, 0), both facing +x. The object is
handled around x = 0.45, y = 0, z = 0.15-0.5 and the mock camera looks at it from +x.
"""
