"""Social-navigation layer of splatsearch (DWA, CoNVOI, pedestrian simulation, metrics).

Not implemented yet: see the social-navigation issue in the tracker."""
