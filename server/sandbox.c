/*
 * sandbox.c - a render worker's Landlock confinement (sandbox.h).
 */
#define _GNU_SOURCE
#include "sandbox.h"

#include <errno.h>
#include <fcntl.h>
#include <linux/landlock.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <unistd.h>

/* Rights of later Landlock ABIs than Debian 12's header knows. */
#ifndef LANDLOCK_ACCESS_FS_TRUNCATE
#define LANDLOCK_ACCESS_FS_TRUNCATE (1ULL << 14)
#endif

#define READ_RIGHTS (LANDLOCK_ACCESS_FS_READ_FILE | LANDLOCK_ACCESS_FS_READ_DIR)
#define FILE_RIGHTS                                                                                \
    (LANDLOCK_ACCESS_FS_EXECUTE | LANDLOCK_ACCESS_FS_READ_FILE | LANDLOCK_ACCESS_FS_WRITE_FILE |   \
     LANDLOCK_ACCESS_FS_TRUNCATE)

/* System folders a process of ours reads (its libraries, /proc, CPU
 * topology in /sys, /dev/null and /dev/urandom) and may run programs from. */
static const char *const SYSTEM_DIRS[] = {"/usr", "/lib", "/lib32", "/lib64", "/libx32", "/bin",
                                          "/sbin", "/etc", "/proc", "/sys", "/dev"};

/* Adds "access beneath path" to the ruleset; a path that does not exist is
 * skipped (no rule is needed to be refused it). A file gets only the rights
 * that apply to files. */
static int allow(int ruleset, const char *path, uint64_t access, uint64_t handled, mr_error *err)
{
    int fd = open(path, O_PATH | O_CLOEXEC);
    if (fd < 0) {
        if (errno == ENOENT || errno == ENOTDIR)
            return MR_OK;
        return mr_error_set(err, MR_ERR_IO, "sandbox: %s: %s", path, strerror(errno));
    }
    struct stat st;
    if (fstat(fd, &st) == 0 && !S_ISDIR(st.st_mode))
        access &= FILE_RIGHTS;
    struct landlock_path_beneath_attr rule = {.allowed_access = access & handled, .parent_fd = fd};
    long rc = syscall(SYS_landlock_add_rule, ruleset, LANDLOCK_RULE_PATH_BENEATH, &rule, 0);
    int e = errno;
    close(fd);
    if (rc != 0)
        return mr_error_set(err, MR_ERR_IO, "sandbox: rule for %s: %s", path, strerror(e));
    return MR_OK;
}

int mr_sandbox_apply(const char *data_dir, const char *const *asset_roots, size_t root_count,
                     const char *exe, mr_error *err)
{
    long abi = syscall(SYS_landlock_create_ruleset, NULL, 0, LANDLOCK_CREATE_RULESET_VERSION);
    if (abi < 1)
        return mr_error_set(err, MR_ERR_NOT_FOUND, "sandbox: this kernel has no Landlock (%s)",
                            strerror(errno));
    uint64_t handled = LANDLOCK_ACCESS_FS_EXECUTE | LANDLOCK_ACCESS_FS_WRITE_FILE |
                       LANDLOCK_ACCESS_FS_READ_FILE | LANDLOCK_ACCESS_FS_READ_DIR |
                       LANDLOCK_ACCESS_FS_REMOVE_DIR | LANDLOCK_ACCESS_FS_REMOVE_FILE |
                       LANDLOCK_ACCESS_FS_MAKE_CHAR | LANDLOCK_ACCESS_FS_MAKE_DIR |
                       LANDLOCK_ACCESS_FS_MAKE_REG | LANDLOCK_ACCESS_FS_MAKE_SOCK |
                       LANDLOCK_ACCESS_FS_MAKE_FIFO | LANDLOCK_ACCESS_FS_MAKE_BLOCK |
                       LANDLOCK_ACCESS_FS_MAKE_SYM;
    if (abi >= 2)
        handled |= LANDLOCK_ACCESS_FS_REFER;
    if (abi >= 3)
        handled |= LANDLOCK_ACCESS_FS_TRUNCATE;
    /* what derived data needs: files written to a temporary name and
     * renamed over (util/file_io.h), old ones replaced */
    uint64_t read_write = READ_RIGHTS | LANDLOCK_ACCESS_FS_WRITE_FILE | LANDLOCK_ACCESS_FS_MAKE_REG |
                          LANDLOCK_ACCESS_FS_MAKE_DIR | LANDLOCK_ACCESS_FS_REMOVE_FILE |
                          LANDLOCK_ACCESS_FS_REMOVE_DIR | LANDLOCK_ACCESS_FS_REFER |
                          LANDLOCK_ACCESS_FS_TRUNCATE;
    struct landlock_ruleset_attr attr = {.handled_access_fs = handled};
    int ruleset = (int)syscall(SYS_landlock_create_ruleset, &attr, sizeof attr, 0);
    if (ruleset < 0)
        return mr_error_set(err, MR_ERR_IO, "sandbox: landlock_create_ruleset: %s", strerror(errno));
    int rc = MR_OK;
    for (size_t i = 0; i < sizeof SYSTEM_DIRS / sizeof *SYSTEM_DIRS && rc == MR_OK; i++)
        rc = allow(ruleset, SYSTEM_DIRS[i], READ_RIGHTS | LANDLOCK_ACCESS_FS_EXECUTE, handled, err);
    if (rc == MR_OK && exe)
        rc = allow(ruleset, exe, READ_RIGHTS | LANDLOCK_ACCESS_FS_EXECUTE, handled, err);
    for (size_t i = 0; i < root_count && rc == MR_OK; i++)
        rc = allow(ruleset, asset_roots[i], READ_RIGHTS, handled, err);
    char path[4200];
    if (rc == MR_OK) {
        snprintf(path, sizeof path, "%s/assets", data_dir);
        rc = allow(ruleset, path, READ_RIGHTS, handled, err);
    }
    /* each kind's derived-data folder, made now: it cannot be made later */
    for (size_t i = 0; i < mr_kind_count() && rc == MR_OK; i++) {
        const mr_kind *k = mr_kind_at(i);
        if (!mr_kind_keeps_derived(k))
            continue;
        snprintf(path, sizeof path, "%s/%s", data_dir, mr_kind_name(k));
        if ((rc = mr_fs_make_dirs(path, "derived-data folder", err)) == MR_OK)
            rc = allow(ruleset, path, read_write, handled, err);
    }
    if (rc == MR_OK && prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0)
        rc = mr_error_set(err, MR_ERR_IO, "sandbox: no_new_privs: %s", strerror(errno));
    if (rc == MR_OK && syscall(SYS_landlock_restrict_self, ruleset, 0) != 0)
        rc = mr_error_set(err, MR_ERR_IO, "sandbox: landlock_restrict_self: %s", strerror(errno));
    close(ruleset);
    return rc;
}
