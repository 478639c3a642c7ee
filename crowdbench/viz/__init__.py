"""Visualisation beside the evaluation: rerun recordings of episodes (``record``), static trajectory
figures and training curves (``figures``). Nothing here is imported unless asked for (``viz.record=true``,
``crowdbench viz``, ``crowdbench plot``); evaluation reaches it only through its recorder hook."""
