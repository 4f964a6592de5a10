"""The pod engine: what a sim pod runs (the ``pod`` install extra). The task registry and its envs
(``tasks``), the task-grouped worker pool (``sim``) and the renderer (``render``, ``batch_render``,
``mesh_lod``). The trainer's client never imports this package."""
