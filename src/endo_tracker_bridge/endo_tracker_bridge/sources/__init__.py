"""Tracker sources: each turns one tracker protocol into :class:`TrackerSample` objects.

* :mod:`.ros` — a ``geometry_msgs/PoseStamped`` topic from a third-party driver;
* :mod:`.igtl` — an OpenIGTLink client for TRANSFORM messages (PLUS, 3D Slicer);
* :mod:`.ndi` — NDI Polaris, Vega or Aurora through scikit-surgerynditracker;
* :mod:`.csv` — a comma- or tab-separated tracker log replayed with its own stamps.

The ROS source is driven by its subscription; the others read on a thread of
their own (:class:`.background.BackgroundSource`) and hand raw items to the
node, which converts each one with ``to_sample`` inside its input guard.
"""
