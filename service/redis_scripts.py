"""The Redis session store's Lua scripts: each change of a session is one atomic call that checks before it writes.

Every write of a session is a compare-and-set on its `ver` field (`session_codec.cas_token`), so a change by another
replica meanwhile is detected instead of overwritten. EVAL, not EVALSHA: no script-cache round trip, and a promoted
replica needs no script loaded.
"""

from __future__ import annotations

from gmt.service import resp

# KEYS: live, session hash, its timeline list, its recording list. ARGV: now, max sessions, id, key TTL ms, the
# number c of timeline entries, the c entries, then field/value pairs. Returns -1 when created, -2 when a live
# session has the id, else the live count that made the store full.
CREATE = """
if redis.call('ZSCORE', KEYS[1], ARGV[3]) and redis.call('EXISTS', KEYS[2]) == 1 then return -2 end
local n = redis.call('ZCARD', KEYS[1])
if n >= tonumber(ARGV[2]) then return n end
redis.call('ZADD', KEYS[1], ARGV[1], ARGV[3])
redis.call('DEL', KEYS[2], KEYS[3], KEYS[4])
local c = tonumber(ARGV[5])
redis.call('HSET', KEYS[2], unpack(ARGV, 6 + c))
redis.call('PEXPIRE', KEYS[2], ARGV[4])
if c > 0 then
  redis.call('RPUSH', KEYS[3], unpack(ARGV, 6, 5 + c))
  redis.call('PEXPIRE', KEYS[3], ARGV[4])
end
return -1
"""

# Many sessions' changes in one call (one per session on Redis Cluster, where one call may touch one slot only).
# KEYS: per session its hash, then the lists its change appends to (its timeline, its recording: 0 to 2 keys, all
# in the session's slot). ARGV: key TTL ms, then per session: the expected `ver` ('' = any), the number n of
# fields, the number m of lists, the n field/value pairs, then per list the number c of values and the c values.
# The fields are written and the values appended only if the compare-and-set passes; an appended list's TTL is set
# again, the hash's is not (each replica's sweep sets the TTLs of the sessions it served, `RedisSessionStore.sweep`:
# a PEXPIRE per act cost a quarter of the script's time and one more command for every replica and the AOF).
# Returns per session 0 when written, -1 when the session is gone (never revived), -2 when another writer came first.
SAVE = """
local ttl, a, k, out = ARGV[1], 2, 1, {}
while k <= #KEYS do
  local key, expect, n, m = KEYS[k], ARGV[a], tonumber(ARGV[a + 1]), tonumber(ARGV[a + 2])
  a = a + 3
  local cur = redis.call('HGET', key, 'ver')
  local ok = cur and (expect == '' or cur == expect)
  if ok then
    redis.call('HSET', key, unpack(ARGV, a, a + 2 * n - 1))
  end
  a = a + 2 * n
  for j = 1, m do
    local c = tonumber(ARGV[a])
    if ok then
      redis.call('RPUSH', KEYS[k + j], unpack(ARGV, a + 1, a + c))
      redis.call('PEXPIRE', KEYS[k + j], ttl)
    end
    a = a + 1 + c
  end
  if not cur then out[#out + 1] = -1 elseif not ok then out[#out + 1] = -2 else out[#out + 1] = 0 end
  k = k + 1 + m
end
return out
"""

# KEYS: live, session hash, timeline, recording, tombstone. ARGV: the expected `ver`, id, tombstone TTL s.
# Removes the session (and marks it closed) only if it has not changed; returns 0, -1 (gone) or -2 (changed).
CLOSE = """
local cur = redis.call('HGET', KEYS[2], 'ver')
if not cur then return -1 end
if cur ~= ARGV[1] then return -2 end
redis.call('DEL', KEYS[2], KEYS[3], KEYS[4])
redis.call('ZREM', KEYS[1], ARGV[2])
redis.call('SET', KEYS[5], 'closed', 'EX', ARGV[3])
return 0
"""


def flat(fields: dict[str, bytes]) -> list:
    """`fields` as the field/value pairs a script's ARGV (or HSET) takes."""
    out: list = []
    for k, v in fields.items():
        out += [k, v]
    return out


def save_entry(expect: bytes, fields: dict[str, bytes], lists: list[list[bytes]]) -> tuple[bytes, int]:
    """One session's `SAVE` arguments (after its keys: the hash, then one per list in `lists`, each list's values
    appended), as RESP bulk strings, and how many: the expected `ver`, n, m, the n field/value pairs, per list c and
    its c values."""
    out = [resp.bulk([expect, b"%d" % len(fields), b"%d" % len(lists)]), resp.pairs(fields)]
    count = 3 + 2 * len(fields)
    for values in lists:
        out.append(resp.bulk([len(values), *values]))
        count += 1 + len(values)
    return b"".join(out), count


def save_command(entries: list[tuple[list, bytes, int]], ttl_ms: int) -> resp.Encoded:
    """One `SAVE` call writing every (keys, encoded arguments, their count) entry (`RedisSessionStore._encode`)."""
    keys = [k for ks, _, _ in entries for k in ks]
    head = resp.bulk(["EVAL", SAVE, len(keys), *keys, ttl_ms])
    return resp.command(len(keys) + 4 + sum(n for _, _, n in entries), head, *(a for _, a, _ in entries))
