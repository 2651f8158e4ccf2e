"""PTAM on a camera phone (Klein & Murray 2009): keyframe monocular SLAM, plain numpy/OpenCV/gtsam.

Modules (one idea each):

* :mod:`.camera`: the pinhole camera, pyramid coordinates and the rolling-shutter row time.
* :mod:`.slam_map`: keyframes, map points, measurements and the lock shared by the two threads.
* front end (tracking thread): pyramid/corners (sec. 3.1), rotation prior (sec. 4), patch search
  (sec. 4), pose update, initialiser (sec. 5.1), relocaliser, tracker.
* back end (mapping thread): partially initialised points (sec. 5.2), bundle adjustment with gtsam,
  measurement and keyframe culling (sec. 3.2, 3.3), rolling-shutter correction (sec. 6), map maker;
  the frame gate lets the mapping thread's steps run only while the tracker waits for a frame
  (sec. 3).

Pose convention (as everywhere in ar_tracking, ``R_a_b`` maps b coordinates into a): a keyframe or
frame pose is ``R_c_w, t_c_w`` with ``x_c = R_c_w @ x_w + t_c_w``; the camera in the map frame is
``R_w_c = R_c_w.T``, ``p_w_c = -R_c_w.T @ t_c_w``. Camera frame: camera_optical (z forward, x
right, y down). The map frame ``slam_map`` is the first keyframe's camera frame; its scale is set
at initialisation (the initial plane at depth 1).
"""
