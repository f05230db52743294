"""Scene rows: a scene's stage, state, own log and child job ids (service.scene_supervisor moves them on)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import delete, func, select

from service.kinds import TERMINAL_STATES
from service.store.database import Database
from service.store.tables import SCENE_CHILD_COLUMNS, Job, Scene, utcnow


class SceneRows(Database):
    """The `scenes` table."""

    def create_scene(self, scene: Scene) -> Scene:
        with self._sessions.begin() as session:
            session.add(scene)
        return scene

    def get_scene(self, scene_id: str) -> Scene | None:
        with self._sessions() as session:
            return session.get(Scene, scene_id)

    def list_scenes(
        self, *, state: str | None = None, owner: str | None = None, limit: int = 50, offset: int = 0
    ) -> tuple[list[Scene], int]:
        """Scenes newest first; only `owner`'s (the owner of their reconstruction job) when given."""
        query = select(Scene) if state is None else select(Scene).where(Scene.state == state)
        if owner is not None:
            query = query.join(Job, Job.id == Scene.reconstruction_job_id).where(Job.owner == owner)
        with self._sessions() as session:
            total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
            rows = session.scalars(
                query.order_by(Scene.created_at.desc(), Scene.id).limit(limit).offset(offset)
            ).all()
        return list(rows), int(total)

    def update_scene(self, scene_id: str, *, log: str | None = None, **values: Any) -> Scene | None:
        """Sets the fields given and appends `log` to the scene's own log lines; the scene after."""
        with self._sessions.begin() as session:
            scene = session.get(Scene, scene_id, with_for_update=True)
            if scene is None:
                return None
            for name, value in values.items():
                setattr(scene, name, value)
            if log is not None:
                scene.log = [*scene.log, f"{utcnow():%Y-%m-%d %H:%M:%S} {log}"]
            return scene

    def expired_scenes(self, finished_before: datetime, limit: int = 100) -> list[Scene]:
        """Finished scenes that ended before the cut-off, oldest first, whose child jobs have all ended and
        none is pinned (pinning any child job keeps its whole scene)."""
        with self._sessions() as session:
            query = (
                select(Scene)
                .where(Scene.state.in_(list(TERMINAL_STATES)), Scene.finished_at < finished_before)
                .order_by(Scene.finished_at)
                .limit(limit)
            )
            scenes = list(session.scalars(query).all())
        return [
            scene
            for scene in scenes
            if all(
                job.state in TERMINAL_STATES and not job.pinned
                for job in map(self.get, self.scene_job_ids(scene))
                if job is not None
            )
        ]

    def scene_job_ids(self, scene: Scene) -> list[str]:
        """A scene's child jobs and the jobs they retried, last stage first (the order to delete them)."""
        ids = []
        for column in reversed(SCENE_CHILD_COLUMNS):
            job_id = getattr(scene, column.key)
            while job_id and (job := self.get(job_id)) is not None:
                ids.append(job_id)
                job_id = job.retry_of
        return ids

    def delete_scene(self, scene_id: str) -> bool:
        with self._sessions.begin() as session:
            return session.execute(delete(Scene).where(Scene.id == scene_id)).rowcount == 1
