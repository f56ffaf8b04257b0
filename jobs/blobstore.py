"""Where a job's files are kept: the local data directory, or an S3-compatible object store.

One interface, two backends, chosen by `LIGHTFIELD_STORAGE_URL`:

* unset: `LocalStore` on the data directory (`LIGHTFIELD_DATA_DIR`): keys are paths below it,
  exactly where `jobs.storage.JobPaths` puts files, so every transfer is a no-op and the
  embedded mode (`make demo`) works as it always did;
* `s3://bucket/prefix`: `S3Store` through boto3 (credentials, endpoint and region from the
  standard AWS variables: `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_ENDPOINT_URL`,
  `AWS_DEFAULT_REGION`, so MinIO, Ceph RGW, R2 and GCS interop work unchanged). Each host then
  works in its own local directory; the store is the only thing hosts share besides Redis.

Writes are atomic: a local file is written beside its target and renamed; an object is one
PUT of a finished file (S3 never shows a half-written object). Every object carries the
SHA-256 of its bytes (`x-amz-meta-sha256`), checked after every download, so a copy on a
host is the stored object or nothing. The store failing (unreachable, 5xx, refused) raises
`StorageUnavailable`, an OSError with errno EIO: the API answers 503 `storage_unavailable`
and a worker waits it out (jobs.storage.is_storage_error), as for a local disk fault.

Why boto3: the reference client, with the standard variables and retries built in, and the
client moto's server mode (the tests) is built against; obstore/fsspec would add a layer for
nothing this needs (whole-object GET/PUT/LIST/DELETE).
"""
from __future__ import annotations

import errno
import hashlib
import os
import shutil
import uuid
from pathlib import Path
from urllib.parse import urlparse

SHA_META = "sha256"
_CHUNK = 1 << 20


class StorageUnavailable(OSError):
    """The object store cannot be reached or refused a request (errno EIO)."""

    def __init__(self, message: str):
        super().__init__(errno.EIO, message)


class ObjectCorrupt(ValueError):
    """A downloaded object does not match the SHA-256 recorded when it was stored."""


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def _tmp_beside(path: Path) -> Path:
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.part")


class BlobStore:
    """Whole files by key ('artefacts/<tenant-hash>/<job>/lightfield/field.safetensors')."""

    url = ""
    is_local = False

    def local_path(self, key: str) -> Path | None:
        """The file itself when the store is this host's directory (no copy needed), else None."""
        return None

    def put_file(self, key: str, path: Path) -> None:
        raise NotImplementedError

    def get_file(self, key: str, dest: Path) -> bool:
        """Download `key` to `dest` atomically (verified); False when there is no such object."""
        raise NotImplementedError

    def exists(self, key: str) -> bool:
        raise NotImplementedError

    def list(self, prefix: str) -> list[str]:
        raise NotImplementedError

    def delete(self, keys: list[str]) -> None:
        raise NotImplementedError

    def delete_prefix(self, prefix: str) -> bool:
        """Delete every object below `prefix`; True when nothing is left."""
        try:
            keys = self.list(prefix)
            if keys:
                self.delete(keys)
            return not self.list(prefix)
        except OSError:
            return False


class LocalStore(BlobStore):
    is_local = True

    def __init__(self, root: Path):
        self.root = Path(root)
        self.url = f"file://{self.root.resolve()}"

    def _path(self, key: str) -> Path:
        parts = [p for p in key.split("/") if p]
        if not parts or any(p in (".", "..") for p in parts):
            raise ValueError(f"bad storage key {key!r}")
        return self.root.joinpath(*parts)

    def local_path(self, key: str) -> Path | None:
        return self._path(key)

    def put_file(self, key: str, path: Path) -> None:
        target = self._path(key)
        if Path(path).resolve() == target.resolve():
            return
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = _tmp_beside(target)
        try:
            shutil.copyfile(path, tmp)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)

    def get_file(self, key: str, dest: Path) -> bool:
        source = self._path(key)
        if not source.is_file():
            return False
        if Path(dest).resolve() != source.resolve():
            Path(dest).parent.mkdir(parents=True, exist_ok=True)
            tmp = _tmp_beside(Path(dest))
            try:
                shutil.copyfile(source, tmp)
                os.replace(tmp, dest)
            finally:
                tmp.unlink(missing_ok=True)
        return True

    def exists(self, key: str) -> bool:
        return self._path(key).is_file()

    def list(self, prefix: str) -> list[str]:
        base = self._path(prefix)
        if not base.is_dir():
            return []
        return sorted(str(p.relative_to(self.root).as_posix()) for p in base.rglob("*") if p.is_file())

    def delete(self, keys: list[str]) -> None:
        for key in keys:
            self._path(key).unlink(missing_ok=True)

    def delete_prefix(self, prefix: str) -> bool:
        base = self._path(prefix)
        shutil.rmtree(base, ignore_errors=True)
        return not os.path.lexists(base)


class S3Store(BlobStore):
    def __init__(self, bucket: str, prefix: str = "", client=None):
        self.bucket, self.prefix = bucket, prefix.strip("/")
        self.url = f"s3://{bucket}/{self.prefix}"
        self._client = client

    @property
    def client(self):
        if self._client is None:
            import boto3  # noqa: PLC0415 — boto3 is heavy: imported when used
            from botocore.config import Config  # noqa: PLC0415 — botocore is heavy: imported when used

            # endpoint, credentials and region from the standard AWS variables (AWS_ENDPOINT_URL ...)
            self._client = boto3.client("s3", config=Config(
                retries={"max_attempts": 4, "mode": "standard"}, connect_timeout=5, read_timeout=30,
                s3={"addressing_style": "path"}))
        return self._client

    def _key(self, key: str) -> str:
        return f"{self.prefix}/{key}" if self.prefix else key

    def _call(self, what: str, fn, *args, **kwargs):
        from botocore.exceptions import BotoCoreError, ClientError  # noqa: PLC0415 — botocore is heavy: imported when used

        try:
            return fn(*args, **kwargs)
        except ClientError as exc:
            code = exc.response.get("Error", {}).get("Code", "")
            if code in ("404", "NoSuchKey", "NotFound"):
                raise FileNotFoundError(errno.ENOENT, f"no object {what}") from None
            raise StorageUnavailable(f"object store refused {what} ({code or 'error'})") from None
        except BotoCoreError as exc:
            raise StorageUnavailable(f"object store unreachable during {what} ({type(exc).__name__})") from None

    def put_file(self, key: str, path: Path) -> None:
        digest = file_sha256(path)
        with open(path, "rb") as f:  # one PUT of the finished file: never visible half-written
            self._call(f"PUT {key}", self.client.put_object, Bucket=self.bucket, Key=self._key(key), Body=f,
                       Metadata={SHA_META: digest})

    def get_file(self, key: str, dest: Path) -> bool:
        dest = Path(dest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = _tmp_beside(dest)
        try:
            try:
                obj = self._call(f"GET {key}", self.client.get_object, Bucket=self.bucket, Key=self._key(key))
            except FileNotFoundError:
                return False
            h = hashlib.sha256()
            with open(tmp, "wb") as f:
                body = obj["Body"]
                try:
                    for block in iter(lambda: body.read(_CHUNK), b""):
                        h.update(block)
                        f.write(block)
                except Exception as exc:  # the connection broke mid-body
                    raise StorageUnavailable(f"object store: GET {key} broke off ({type(exc).__name__})") from None
            expected = obj.get("Metadata", {}).get(SHA_META)
            if expected and h.hexdigest() != expected:
                raise ObjectCorrupt(f"{key.rsplit('/', 1)[-1]}: the stored object does not match its SHA-256")
            os.replace(tmp, dest)
            return True
        finally:
            tmp.unlink(missing_ok=True)

    def exists(self, key: str) -> bool:
        try:
            self._call(f"HEAD {key}", self.client.head_object, Bucket=self.bucket, Key=self._key(key))
            return True
        except FileNotFoundError:
            return False

    def list(self, prefix: str) -> list[str]:
        full = self._key(prefix.rstrip("/") + "/")
        keys: list[str] = []
        token = None
        while True:
            kwargs = {"Bucket": self.bucket, "Prefix": full, **({"ContinuationToken": token} if token else {})}
            page = self._call(f"LIST {prefix}", self.client.list_objects_v2, **kwargs)
            keys += [o["Key"][len(self.prefix) + 1:] if self.prefix else o["Key"] for o in page.get("Contents", [])]
            if not page.get("IsTruncated"):
                return keys
            token = page["NextContinuationToken"]

    def delete(self, keys: list[str]) -> None:
        for start in range(0, len(keys), 1000):
            batch = [{"Key": self._key(k)} for k in keys[start:start + 1000]]
            self._call(
                "DELETE", self.client.delete_objects, Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True}
            )


def store_for(storage_url: str | None, data_dir: Path) -> BlobStore:
    """The store `LIGHTFIELD_STORAGE_URL` names (unset: the local data directory)."""
    if not storage_url:
        return LocalStore(data_dir)
    url = urlparse(storage_url)
    if url.scheme == "s3" and url.netloc:
        return S3Store(url.netloc, url.path)
    if url.scheme == "file":
        return LocalStore(Path(url.path))
    raise ValueError(f"LIGHTFIELD_STORAGE_URL must be s3://bucket/prefix or unset, got {storage_url!r}")
