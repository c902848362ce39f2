"""Durable, append-only recording of real-robot transitions, and the reader that gives them back.

What it is for
--------------
Everything the loop learns about the real system comes from transitions recorded on it: sysid
fits ``PhysParams`` to them, visual real2sim fits cameras and objects to their images, sim2real
trains the residual policy and refits the hybrid dynamics on them. Real rollouts are the expensive
resource, and a collection run can die at any moment (e-stop, OOM killer, a pre-empted job,
SIGKILL). So every transition is made durable *as it happens*: a process killed mid-episode
leaves a readable dataset that has lost at most the transition being written, and
``DatasetWriter`` on the same directory continues it (``twinrl collect --resume``).

Format, and why
---------------
A dataset is a directory::

    meta.json                     written once, atomically (tmp file, fsync, os.replace)
    chunk-SSSSS-CCCCC.twr         closed chunk C of writer session S
    chunk-SSSSS-CCCCC.twr.open    chunk being written, or left behind by a killed writer
    .lock                         flock(2) held by the one live writer

A chunk is an 8-byte file magic followed by self-delimiting records::

    prefix, 28 bytes little-endian: b"TRec" | header length u32 | body length u64
                                    | header crc32 | body crc32 | crc32 of these 24 bytes
    header: UTF-8 JSON (kind, episode, step, time, reward, flags, info, array names/dtypes/shapes)
    body:   raw little-endian bytes of the arrays (obs, action, next_obs, images), in header order

Why this rather than the alternatives:

* **One record, one write, nothing rewritten.** ``add`` builds a whole record and hands it to the
  kernel with ``os.write`` on an unbuffered descriptor before returning, so a completed ``add``
  survives SIGKILL in every ``sync`` mode; ``sync`` only decides when ``os.fsync`` also makes it
  survive power loss (every transition, every episode end, or never). Bytes once written are never
  touched again, so a crash can only leave a torn tail.
* **Self-delimiting and checksummed.** The prefix's own CRC makes the lengths trustworthy; the
  header and body CRCs catch torn or flipped bytes. A torn tail is recognised and dropped; a
  damaged record in the middle is skipped and the reader resynchronises on the next valid prefix,
  so every intact transition is still returned.
* **"Closed" and "killed" are told apart.** A chunk is renamed from ``.twr.open`` to ``.twr`` only
  after its footer (its record count) is written. A torn tail in an ``.open`` chunk is the expected
  trace of a killed writer and is not an error; a ``.twr`` chunk without its footer, or whose count
  disagrees, was damaged afterwards and is reported, naming the file.
* **Chunks** bound the memory a reader needs per file and what one bad file can cost; every writer
  session starts a new chunk, so a resumed run never appends behind a torn tail.
* **No new dependency, no pickle.** JSON plus raw arrays, readable from any language. HDF5 (h5py,
  and Minari's default storage) updates its metadata in place, so a writer killed mid-flush can
  leave the whole file unreadable; ``.npz`` is a zip whose directory is written last, at close.

Episodes: an ``add`` with ``terminated`` or ``truncated`` ends the episode, ``end_episode()`` ends
it without either (an ``end`` marker record). An episode is *complete* when its steps run 0..n-1
without a gap and it was ended; the episode a killed or closed writer left open is returned,
flagged incomplete.

Modules
-------
``writer`` (``DatasetWriter``: durable appends, locking, resuming), ``reader`` (``read``,
``Dataset``, ``Episode``), ``_format`` (names, magics, the record codec and chunk scan both share)
and ``_checks`` (the errors, and the checks of a writer's inputs and of ``meta.json``).
``minari`` converts both ways to Minari's datasets (``to_minari``, ``read_minari``; the optional
``minari`` extra, imported only when used).
"""

from twinrl.real.dataset._checks import DatasetError, DatasetMismatch
from twinrl.real.dataset._format import (
    FILE_MAGIC,
    FORMAT,
    IMAGE_DTYPES,
    LOCK_FILE,
    META_FILE,
    PREFIX_SIZE,
    RECORD_MAGIC,
    VERSION,
)
from twinrl.real.dataset.reader import Dataset, Episode, read
from twinrl.real.dataset.writer import DatasetWriter, Sync

__all__ = ["Dataset", "DatasetError", "DatasetMismatch", "DatasetWriter", "Episode", "read",
           "IMAGE_DTYPES", "VERSION", "FORMAT", "META_FILE", "LOCK_FILE", "FILE_MAGIC",
           "RECORD_MAGIC", "PREFIX_SIZE", "Sync"]
