"""Contact physics, linear elastic, below both the network and the tracker: the Green's
functions of the case's FE model for loads on the skin (:mod:`.greens`), the network's physics
baseline (:mod:`.baseline`), the projection onto the measured contact (:mod:`.projection`) and
the displacement of a few points (lesions) for a contact set (:mod:`.lesions`).
"""
