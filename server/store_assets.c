/*
 * store_assets.c - content-addressed assets in the store (store.h,
 * store_internal.h): DIR/assets/<sha256>, written through a unique
 * temporary while the upload is hashed, renamed under its hash when
 * complete, and recorded in the assets table.
 */
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "store_internal.h"
#include "microray.h"

/* ---- assets ----------------------------------------------------------------- */

struct mr_asset_upload {
    mr_fs_atomic file; /* assets/.upload.tmpXXXXXX, renamed to its hash */
    uint64_t size;
    mr_sha256 hash;
};

int mr_store_asset_upload_begin(mr_store *st, mr_asset_upload **out, mr_error *err)
{
    *out = NULL;
    mr_asset_upload *up = calloc(1, sizeof *up);
    if (!up)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory starting an upload");
    char name[STORE_PATH_MAX];
    int rc = store_path_join(name, sizeof name, err, "%s/assets/.upload", st->dir);
    /* A unique temporary: two uploads of the same bytes at once must not
     * write into one file. */
    if (rc == MR_OK)
        rc = mr_fs_atomic_begin(&up->file, name, "asset upload", err);
    if (rc < 0) {
        free(up);
        return rc;
    }
    mr_sha256_init(&up->hash);
    *out = up;
    return MR_OK;
}

int mr_store_asset_upload_write(mr_asset_upload *up, const void *data, size_t size, mr_error *err)
{
    int rc = mr_fs_atomic_write(&up->file, data, size, "asset upload", err);
    if (rc < 0)
        return rc;
    mr_sha256_update(&up->hash, data, size);
    up->size += size;
    return MR_OK;
}

void mr_store_asset_upload_abort(mr_asset_upload *up)
{
    if (!up)
        return;
    mr_fs_atomic_abort(&up->file);
    free(up);
}

int mr_store_asset_upload_finish(mr_store *st, mr_asset_upload *up, char id[MR_ASSET_ID_LEN + 1],
                                 bool *existed, mr_error *err)
{
    if (existed)
        *existed = false;
    id[0] = '\0';
    uint8_t digest[32];
    char hex[MR_ASSET_ID_LEN + 1];
    mr_sha256_final(&up->hash, digest);
    mr_hex_encode(digest, sizeof digest, hex);
    uint64_t size = up->size;

    char dir[STORE_PATH_MAX], path[STORE_PATH_MAX];
    int rc;
    if ((rc = store_path_join(dir, sizeof dir, err, "%s/assets", st->dir)) < 0 ||
        (rc = store_path_join(path, sizeof path, err, "%s/%s", dir, hex)) < 0) {
        mr_store_asset_upload_abort(up);
        return rc;
    }
    /* A file of the right size under its hash is taken as complete: it
     * only ever appears there by rename after an fsync. */
    struct stat sb;
    bool present = stat(path, &sb) == 0 && S_ISREG(sb.st_mode) && (uint64_t)sb.st_size == size;
    if (present) {
        mr_store_asset_upload_abort(up);
    } else {
        rc = mr_fs_atomic_commit(&up->file, path, "asset upload", err); /* ends the write */
        free(up);
        if (rc < 0)
            return rc;
    }

    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_ASSET_INSERT);
    rc = store_exec_bound(st, s,
                          sqlite3_bind_text(s, 1, hex, -1, SQLITE_STATIC) |
                              sqlite3_bind_int64(s, 2, (sqlite3_int64)size) |
                              sqlite3_bind_double(s, 3, store_now()),
                          "record asset", err);
    bool known = rc == MR_OK && sqlite3_changes(st->db) == 0;
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;
    if (existed)
        *existed = known;
    memcpy(id, hex, sizeof hex);
    return MR_OK;
}

int mr_store_asset_put(mr_store *st, const void *data, size_t size, char id[MR_ASSET_ID_LEN + 1],
                       bool *existed, mr_error *err)
{
    if (existed)
        *existed = false;
    if (!st || !id || (!data && size > 0))
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_asset_put: missing argument");
    id[0] = '\0';
    mr_asset_upload *up = NULL;
    int rc = mr_store_asset_upload_begin(st, &up, err);
    if (rc == MR_OK && (rc = mr_store_asset_upload_write(up, data, size, err)) < 0)
        mr_store_asset_upload_abort(up);
    else if (rc == MR_OK)
        rc = mr_store_asset_upload_finish(st, up, id, existed, err);
    return rc;
}

int mr_store_asset_path(mr_store *st, const char *id, char *path, size_t path_size, mr_error *err)
{
    if (!st || !path || path_size == 0)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_asset_path: missing argument");
    path[0] = '\0';
    char buf[72];
    /* Only exact hashes become paths: "../x", "a/b", uppercase, short or
     * long strings never reach the file system. */
    if (!mr_hex_is_lower(id, MR_ASSET_ID_LEN))
        return mr_error_set(err, MR_ERR_NOT_FOUND, "no asset '%s' (an asset id is 64 lowercase "
                            "hex digits)", store_printable(id, buf));
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_ASSET_GET);
    int rc = store_step_row(st, s, store_bind_text(s, 1, id), "find asset", err);
    if (rc == 0)
        rc = mr_error_set(err, MR_ERR_NOT_FOUND, "no asset '%s'", id);
    store_stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;
    if ((rc = store_path_join(path, path_size, err, "%s/assets/%s", st->dir, id)) < 0) {
        path[0] = '\0';
        return rc;
    }
    /* A row without its file (removed by hand) is as good as unknown; an
     * upload of the same bytes writes it again. */
    if (access(path, R_OK) != 0) {
        int e = errno;
        path[0] = '\0';
        return mr_error_set(err, MR_ERR_NOT_FOUND, "asset '%s' is recorded but its file is "
                            "unreadable: %s", id, strerror(e));
    }
    return MR_OK;
}

/* ---- listing and deleting ------------------------------------------------ */

static int asset_row(sqlite3_stmt *s, void *row, mr_error *err)
{
    (void)err;
    mr_asset_record *a = row;
    memset(a, 0, sizeof *a);
    store_copy_col(a->id, sizeof a->id, s, 0);
    a->size = (uint64_t)sqlite3_column_int64(s, 1);
    a->created = sqlite3_column_double(s, 2);
    a->last_used = sqlite3_column_double(s, 3);
    a->jobs_active = (size_t)sqlite3_column_int64(s, 4);
    a->seq = sqlite3_column_int64(s, 5);
    return MR_OK;
}

static int no_asset(mr_error *err, const char *id)
{
    char b[72];
    return mr_error_set(err, MR_ERR_NOT_FOUND, "no asset '%s'", store_printable(id, b));
}

int mr_store_asset_get(mr_store *st, const char *id, mr_asset_record *out, mr_error *err)
{
    if (!mr_hex_is_lower(id, MR_ASSET_ID_LEN))
        return no_asset(err, id);
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_ASSET_ROW);
    int rc = store_step_row(st, s, store_bind_text(s, 1, id), "read asset", err);
    if (rc == 1)
        rc = asset_row(s, out, err);
    else if (rc == 0)
        rc = no_asset(err, id);
    store_stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_asset_list(mr_store *st, int64_t before, size_t limit, mr_asset_record **out,
                        size_t *count, int64_t *next, mr_error *err)
{
    *out = NULL;
    *count = 0;
    *next = 0;
    sqlite3_int64 rows_wanted = limit && limit < (size_t)INT64_MAX ? (sqlite3_int64)limit + 1 : -1;
    store_rows rows = {.elem = sizeof **out, .first_cap = 16, .read = asset_row};
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_ASSET_LIST);
    int rc = store_read_rows(st, s,
                             sqlite3_bind_int64(s, 1, before > 0 ? before : 0) |
                                 sqlite3_bind_int64(s, 2, rows_wanted),
                             &rows, "assets", err);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0) {
        free(rows.items);
        return rc;
    }
    *out = rows.items;
    *count = rows.count;
    if (limit && rows.count > limit) {
        *count = limit;
        *next = (*out)[limit - 1].seq;
    }
    return MR_OK;
}

int mr_store_asset_delete(mr_store *st, const char *id, mr_error *err)
{
    if (!mr_hex_is_lower(id, MR_ASSET_ID_LEN))
        return no_asset(err, id);
    char path[STORE_PATH_MAX];
    int rc = store_path_join(path, sizeof path, err, "%s/assets/%s", st->dir, id);
    if (rc < 0)
        return rc;
    pthread_mutex_lock(&st->lock);
    if ((rc = store_tx_begin(st, err)) < 0) {
        pthread_mutex_unlock(&st->lock);
        return rc;
    }
    sqlite3_stmt *s = store_stmt(st, S_ASSET_ACTIVE);
    rc = store_step_row(st, s, store_bind_text(s, 1, id), "find asset", err);
    sqlite3_int64 active = rc == 1 ? sqlite3_column_int64(s, 0) : 0;
    store_stmt_release(s);
    if (rc == 0)
        rc = no_asset(err, id);
    else if (rc == 1 && active > 0)
        rc = mr_error_set(err, MR_ERR_CONFLICT, "asset %s is used by %lld queued or running job%s; "
                          "cancel or delete %s first", id, (long long)active, active == 1 ? "" : "s",
                          active == 1 ? "it" : "them");
    else if (rc == 1) {
        s = store_stmt(st, S_ASSET_DELETE);
        rc = store_exec_bound(st, s, store_bind_text(s, 1, id), "delete asset", err);
    }
    rc = store_tx_end(st, rc, err); /* and unlocks */
    if (rc < 0)
        return rc;
    /* the row first, the file second: a crash in between leaves a file no
     * row names, which an upload of the same bytes reuses */
    if (unlink(path) != 0 && errno != ENOENT)
        return store_io_error(err, "remove asset", path, errno);
    return MR_OK;
}
