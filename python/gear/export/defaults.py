"""Default export settings (a light module: the command line imports it to build its help).

Units: the scene's unit is the models' length unit (metres for the built-in scenes)."""

FACES = 20000  # visual faces per link: a TSDF part mesh has 60k-250k, 20k keeps its shape
DENSITY = 250.0  # kg/m^3 over the convex pieces: light for a solid (particle board ~650)
# because the pieces are solid where real furniture and appliances are hollow panels, and a
# reconstructed wall is thicker than the real one; gives a fridge tens of kg, not a tonne
DAMPING = 1.0  # N*m*s/rad (hinge) or N*s/m (slide): a door let go stops within seconds
FRICTION = 0.1  # N*m or N (MuJoCo frictionloss): holds a joint still against numerical drift
EFFORT = 100.0  # URDF requires effort and velocity limits; nothing in a capture measures them
VELOCITY = 1.0
CONCAVITY = 0.05  # CoACD's concavity threshold, a fraction of the part's size
MAX_PIECES = 32  # convex pieces per link at most
