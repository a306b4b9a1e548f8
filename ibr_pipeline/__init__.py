"""ibr_pipeline: image-based rendering of indoor scenes with reflections.

Implements Xu et al. 2021 (Scalable Image-based Indoor Scene Rendering with Reflections) and
Lochmann et al. 2014 (Real-time Reflective and Refractive Novel-view Synthesis).
Heavy libraries (open3d, torch, pycolmap, moderngl, dask) are imported lazily by the modules that
need them, so `import ibr_pipeline` and `ibr --help` stay fast.
"""
__version__ = "0.1.0"
