"""Calibration of the rig (paper 002 sec. 4; issue 16 item 4): camera intrinsics and pose from
checkerboards (Zhang 2000, :mod:`.checkerboard`), LED positions from highlights in a flat mirror at known
heights (:mod:`.mirror`), LED intensities from a white reference (:mod:`.photometric`); the result is one
``calibration.json`` (:mod:`.rigfile`). The virtual rig renders the targets (:mod:`.targets`).

Targets folder layout (``results/calibration/{rig}/targets/``; for a real rig, put your photos in the
same layout and write ``targets.json`` by hand)::

    targets.json            the description below
    intrinsics/NN.exr       hand-held checkerboard views at different tilts (>= 3, 10-20 recommended)
    pose/board.exr          the same checkerboard lying flat on the sample plane at a known placement
    mirror/*.exr            a front-surface mirror on the sample plane, then on a spacer of known height,
                            one frame per (height, carriage position, lit LED); dark room, linear EXR
    white/*.exr             a white diffuse reference of known albedo on the sample plane, one frame per LED
                            (linear EXR: RAW-decoded, no gamma)
    truth.json              virtual rigs only: the truth the targets were rendered with (tests)

``targets.json``::

    {"version": 1, "rig": NAME, "units": "m",
     "camera": {"width": W, "height": H},
     "saturation": S,                  # the sensor's clip level in the images' units (null: none)
     "noise": {"read_sigma": s},       # optional: sets the highlight and white-reference noise floors
     "prior": {"camera_centre": [x, y, z],    # roughly where the camera is (m): orders the pose board's corners
               "led_home": [[x, y, z], ...]},  # optional, the description's LED positions at steps = 0: LEDs
                                               # the mirror never shows keep them, shifted as the others moved
     "board": {"inner_corners": [cols, rows], "square": METRES},
     "leds": {"count": N},
     "carriage": {"step_length": METRES},     # optional: travel per motor step (1 / (1000 steps_per_mm)), a machine
                                              # constant; fixes the focal length a narrow lens leaves loose
     "intrinsics": [{"file": "intrinsics/00.exr"}, ...],
     "pose": {"file": "pose/board.exr", "origin": [x, y, 0],   # world position of inner corner 0
              "x_axis": [1, 0, 0], "y_axis": [0, 1, 0]},        # along which its columns and rows run
     "mirror": {"heights": [h0, h1], "frames": [{"file", "height", "led", "steps"}, ...]},
     "white": {"albedo": 0.95, "frames": [{"file", "led", "steps", "time"}, ...]}}

Images other than EXR are read with OpenCV (values over the type's maximum); checkerboards may be 8-bit,
the mirror and white frames must be linear. ``time`` is the exposure time of a white frame (the intensity
is in the capture manifest's units per unit time, as the hdr stage merges them).
"""
