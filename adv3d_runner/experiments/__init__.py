"""The paper's experiments on the protocol: ``adv3d experiments TABLE ...`` (:mod:`.cli`) and
the campaign driver behind it (:mod:`.tables`; docs/results.md)."""
