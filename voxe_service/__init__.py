"""The service core shared by the API (``api/``) and the workers (``worker/``).

Settings, the database (engine, sessions, models, migrations), the artifact storage, the stored
scene archive's layout, the job and scene lifecycles both sides write, and the queue contract
(queue and task names, the stage chain, task messages, a Celery app factory and a sender).
``api`` and ``worker`` import this package and ``voxe_core``, never each other; nothing here
imports either of them, and importing a module builds nothing (no engine, no Celery app).
"""
