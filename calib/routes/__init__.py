"""Routes that combine estimators and their verdict into one fit: the joint route
(:func:`~calib.routes.joint.fit_joint`) for static-pose rigs and for logs without static poses
(:mod:`calib.routes.forward_rows`).
"""
