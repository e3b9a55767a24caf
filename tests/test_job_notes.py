"""A job's notes (what its scene holds that was accepted but ignored) are kept in its record,
bounded: repeats dropped, at most MAX_JOB_NOTES, each cut to MAX_NOTE_CHARS, and then one
line counting the rest. Real Redis for the record; the HTTP half is api_tests/test_upload.py."""

from __future__ import annotations

import json

import redis

from worker.settings import Settings
from worker.store import Jobs, keys
from worker.store.record import MAX_JOB_NOTES, MAX_NOTE_CHARS, bounded_notes


def _notes(count: int) -> list[str]:
    return [f"ignored: scene.xml line {i + 2}: <texture type=\"bitmap\">: id 't{i}' (defined but never referenced)"
            for i in range(count)]


def test_notes_within_the_cap_are_kept_as_they_came() -> None:
    notes = _notes(MAX_JOB_NOTES)
    assert bounded_notes(notes) == tuple(notes)
    assert bounded_notes([]) == ()


def test_thousands_of_notes_keep_the_first_distinct_ones_and_count_the_rest() -> None:
    distinct = _notes(3 * MAX_JOB_NOTES + 1000)
    repeated = [note for note in distinct for _ in range(2)]  # each said twice: counted once
    kept = bounded_notes(repeated)
    assert kept[:-1] == tuple(distinct[:MAX_JOB_NOTES])
    assert kept[-1] == f"... and {len(distinct) - MAX_JOB_NOTES} more"


def test_a_long_note_is_cut_and_counted_as_itself() -> None:
    """Two long notes alike in their first MAX_NOTE_CHARS are two notes, cut alike."""
    long = "ignored: scene.xml line 3: <texture type=\"bitmap\">: id '" + "x" * 4 * MAX_NOTE_CHARS
    kept = bounded_notes([long, long + "y", "short", long])
    assert kept[1:] == (kept[0], "short")
    assert len(kept[0]) == MAX_NOTE_CHARS and kept[0].endswith("...") and long.startswith(kept[0][:-3])
    many = bounded_notes(f"{long}{i}" for i in range(MAX_JOB_NOTES + 5))
    assert many[-1] == "... and 5 more" and len(set(many[:-1])) == 1


def test_the_record_keeps_the_bounded_notes_from_its_creation(redis_url: str) -> None:
    jobs = Jobs(redis.Redis.from_url(redis_url))
    notes = _notes(5000)
    job_id = jobs.create({}, Settings(max_passes=1), 8, 8, None, notes=notes)
    record = jobs.get(job_id)
    assert record is not None and record.notes == bounded_notes(notes)
    stored = jobs.r.hget(keys.job(job_id), "notes")
    assert stored is not None and json.loads(stored) == list(record.notes)
    assert len(stored) < (MAX_JOB_NOTES + 1) * (MAX_NOTE_CHARS + 4) < len(json.dumps(notes))
    plain = jobs.create({}, Settings(max_passes=1), 8, 8, None)
    assert jobs.get(plain).notes == ()
