"""OLiVia-Nav (thesis Chapter 3): SC-CLIP -> TPN -> TSM -> the PID follower, in the social
module's scenarios.

Modules: ``render`` (egocentric camera), ``lidar`` (3-D LiDAR sweeps), ``captions`` (the action
vocabulary, template and VLM captions), ``features`` (goal, expert future, action class, one
observation), ``dataset`` (samples from expert episodes), ``tokenizer`` (offline word tokenizer),
``sc_clip`` (image and text encoders, eq 3), ``tpn`` (trajectory prediction, eq 1, 5-6), ``tsm``
(trajectory selection, eq 7), ``llu`` (lifelong update, eq 4), ``planner`` (OliviaNav and its
closed-loop episodes), ``train`` (staged training, checkpoints, Tables I-II) and ``cli`` (the
``splatsearch social train`` / ``eval`` commands).
"""
