"""What the routes do, as keyword-only functions over a session, the settings, the storage and the queue.

Routes parse the request and shape the response; these functions hold the rules (ownership,
quotas, idempotency, scene states) and hand messages to :class:`voxe_service.queue.TaskQueue`.
"""
