"""Navigation layer of splatsearch (occupancy, frontiers, value maps, FMM planning).

Not implemented yet: see the navigation issue in the tracker."""
