"""jsr: joint reconstruction of a static scene and rigidly moving objects from RGB-D.

Method: Caccamo, Ataer-Cansizoglu and Taguchi, "Joint 3D Reconstruction of a Static
Scene and Moving Objects", 3DV 2017.
"""

__version__ = "0.1.0"
